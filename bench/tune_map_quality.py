"""Map-quality vs relation error over parameter sets (docs/tuning.md).

Usage: python bench/tune_map_quality.py CASE PROFILE MAX_SCANS, e.g. bench/aces sparse 250.
"""
import json
import math
import os
import sys
import time

from carto_cli.evaluation.metrics import relation_error
from carto_cli.io.trajectory import Trajectory
from carto_cli.options import apply_overrides, load_options
from carto_cli.pipeline import build
from carto_cli.tuning.objectives import make_cases, map_quality

case, profile, ms = sys.argv[1], sys.argv[2], int(sys.argv[3])
shared = os.environ.get("CARTO_SHARED_DATA", os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"))
d = os.path.join(shared, case)
c = make_cases([d + "/scans.clf.gz"], relations=[d + "/relations.txt"])[0]
online_csm = load_options(profile).trajectory_builder_2d.use_online_correlative_scan_matching
sets = {
    "base": {},
    "num_range_data=10": {
        "trajectory_builder_2d.submaps.num_range_data": 10 if "aces" in case and "dense" not in case else 30},
    "num_range_data=90": {"trajectory_builder_2d.submaps.num_range_data": 90},
    "odometry_weight=1e5": {"pose_graph.optimization_problem.odometry_translation_weight": 1e5,
                            "pose_graph.optimization_problem.odometry_rotation_weight": 1e5},
    "ceres_translation_weight=1e3": {"trajectory_builder_2d.ceres_scan_matcher.translation_weight": 1e3,
                                     "trajectory_builder_2d.ceres_scan_matcher.rotation_weight": 1e3},
    "online_csm=toggled": {"trajectory_builder_2d.use_online_correlative_scan_matching": not online_csm},
    "min_score=0.75": {"pose_graph.constraint_builder.min_score": 0.75},
    "no_loop_closure(sampling=0)": {"pose_graph.constraint_builder.sampling_ratio": 0.0},
}
rows = []
for name, ov in sets.items():
    o = apply_overrides(load_options(profile), ov)
    t = time.time()
    r = build(c.recording(), o, max_scans=ms)
    rel = relation_error(Trajectory.from_poses(r.times, r.poses), c.relations)
    mq = map_quality(r, c.recording(), ms)
    row = dict(name=name, rel_t=rel.translation.mean, rel_r=rel.rotation.mean,
               rel_obj=rel.translation.mean + math.radians(rel.rotation.mean), lc=r.stats["loop_closures"],
               s=time.time() - t, **mq)
    rows.append(row)
    print(json.dumps(row), flush=True)
with open(f"/tmp/validate_{case.replace('/', '_')}.json", "w") as f:
    json.dump(rows, f)
