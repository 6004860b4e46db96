"""What ``carto tune`` writes: the tuned profile, the trials CSV and the report PNG."""
from __future__ import annotations

import csv
import datetime as _dt
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from carto_cli.gmapping import Algorithm
from carto_cli.io.atomic import atomic_output
from carto_cli.io.map_image import write_png
from carto_cli.options import Options, changed_options, load_options
from carto_cli.tuning.objectives import OBJECTIVE_TEXT

__all__ = ["LABEL_WIDTH", "draw_report", "option_labels", "write_profile", "write_trials_csv"]


def _nest(flat: dict[str, Any]) -> dict:
    out: dict = {}
    for key, value in flat.items():
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def write_profile(path: Path, options: Options, *, best=None, objective: str = "", n_trials: int = 0,
                  base_profile=None, overrides=(), tuned: Sequence[str] = (), baseline: float | None = None,
                  time_weight: float = 0.0, max_scans: int | None = None, algorithm: str = "cartographer") -> Path:
    """``options`` as a profile: the keys that differ from the packaged defaults (so the file stands
    alone under ``--profile``, base profile included), with a header saying where it came from."""

    path = Path(path)
    changed = changed_options(options, load_options())
    set_text = (", ".join(f"{k}={v}" for k, v in overrides.items()) if isinstance(overrides, dict)
                else " ".join(f"--set {o}" for o in overrides))
    lines = [
        "# carto tune result: load with --profile " + path.name,
        f"# date: {_dt.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"# base profile: {base_profile or 'default'}" + (f" ({set_text})" if set_text else ""),
        f"# objective: {objective} = {OBJECTIVE_TEXT.get(objective, objective)}"
        + (f" + {time_weight:g} x s/scan" if time_weight else ""),
    ]
    if best is not None:
        lines.append(f"# best value: {best.value:.6g} (trial {best.number} of {n_trials})"
                     + (f"; base options scored {baseline:.6g}" if baseline is not None else ""))
    if algorithm != Algorithm.CARTOGRAPHER:
        # A profile does not choose the mapping system: the tuned values take effect only with the flag.
        lines.append(f"# algorithm: {algorithm} (map with --algorithm {algorithm} --profile {path.name})")
    if max_scans:
        lines.append(f"# scored on the first {max_scans} scans of each recording")
    if tuned:
        lines.append("# tuned options: " + ", ".join(tuned))
    lines.append("# keys below: every option that differs from carto's defaults (base profile + tuned values)")
    body = yaml.safe_dump(_nest(changed), sort_keys=False, default_flow_style=False) if changed else "{}\n"
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n" + body, encoding="utf-8")
    return path


def write_trials_csv(path: Path, trials) -> Path:
    """number, state, value, duration_s, one column per parameter, then the trial's metrics."""
    names: list[str] = []
    attrs: list[str] = []
    for t in trials:
        names += [k for k in t.params if k not in names]
        attrs += [k for k in t.user_attrs if k not in attrs]
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["number", "state", "value", "duration_s"] + names + attrs)
        for t in trials:
            dur = t.duration.total_seconds() if t.duration is not None else ""
            value = "" if t.value is None else repr(float(t.value))
            w.writerow([t.number, t.state.name, value, dur if dur == "" else f"{dur:.3f}"]
                       + [t.params.get(k, "") for k in names] + [t.user_attrs.get(k, "") for k in attrs])
    return path


LABEL_WIDTH = 34  # characters the importance chart's label column holds


def option_labels(names: Sequence[str], width: int = LABEL_WIDTH) -> dict[str, str]:
    """A label of at most ``width`` characters for each option name, distinct for distinct names: the option's own
    name after its section (two parts), more sections where two names would read alike, and sections shortened to
    their initials where the label would not fit (``trajectory_builder_2d.real_time_correlative_scan_matcher.
    linear_search_window`` -> ``rtcsm.linear_search_window``). Cut to the width from the left, four options of one
    matcher all read ``real_time_correlative_scan_matcher``."""
    names = list(dict.fromkeys(names))
    depth = {n: min(2, n.count(".") + 1) for n in names}
    while True:
        labels = {n: _label(n, depth[n], width) for n in names}
        alike: dict[str, list[str]] = {}
        for n, label in labels.items():
            alike.setdefault(label, []).append(n)
        deeper = [n for group in alike.values() if len(group) > 1 for n in group if depth[n] <= n.count(".")]
        if not deeper:
            break
        for n in deeper:
            depth[n] += 1
    # Names that still read alike with every section (possible only where initials or a cut hide the difference)
    # are numbered.
    for group in alike.values():
        for k, n in enumerate(group[1:], start=2):
            tag = f" #{k}"
            labels[n] = labels[n][:width - len(tag)] + tag
    return labels


def _label(name: str, depth: int, width: int) -> str:
    parts = name.split(".")[-depth:]
    for k in range(len(parts)):  # sections shortened from the outermost in, until it fits
        text = ".".join(parts)
        if len(text) <= width:
            return text
        if k < len(parts) - 1:
            parts[k] = "".join(word[:1] for word in parts[k].split("_") if word)
    leaf, room = parts[-1], width - len(parts[-1]) - 1
    if room > 0:  # the option's own name whole, after as much of its sections' initials as fits
        return (".".join(parts[:-1])[:room] + "." if len(parts) > 1 else "") + leaf
    keep = width - 2  # the option's name alone is too long: its middle gives way, both ends stay
    return leaf[:keep // 2] + ".." + leaf[len(leaf) - (keep - keep // 2):]


def draw_report(path: Path, trials, importances: dict[str, float], title: str = "carto tune") -> Path:
    """A PNG: objective per trial with the best-so-far line, and parameter importances (OpenCV)."""
    import cv2
    import optuna

    W, H = 1280, 520
    img = np.full((H, W, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    black, grey, blue, red = (0, 0, 0), (170, 170, 170), (200, 110, 30), (40, 40, 220)
    cv2.putText(img, title, (20, 28), font, 0.65, black, 1, cv2.LINE_AA)
    # ---- history
    x0, y0, x1, y1 = 80, 60, 620, H - 60
    cv2.rectangle(img, (x0, y0), (x1, y1), black, 1)
    cv2.putText(img, "objective per trial (lower is better); red: best so far", (x0, y0 - 10), font, 0.45, black, 1,
                cv2.LINE_AA)
    done = [(t.number, float(t.value)) for t in trials
            if t.state == optuna.trial.TrialState.COMPLETE and t.value is not None and math.isfinite(t.value)]
    n = max([t.number for t in trials], default=0) + 1
    if done:
        vals = np.array([v for _, v in done])
        lo, hi = float(vals.min()), float(np.percentile(vals, 95)) if len(vals) > 4 else float(vals.max())
        if hi <= lo:
            hi = lo + max(abs(lo) * 0.1, 1e-9)
        pad = 0.05 * (hi - lo)
        lo, hi = lo - pad, hi + pad

        def px(i, v):
            x = x0 + int(round((i + 0.5) / n * (x1 - x0)))
            y = y1 - int(round((min(max(v, lo), hi) - lo) / (hi - lo) * (y1 - y0)))
            return x, y

        for i, v in done:
            cv2.circle(img, px(i, v), 4, blue, -1, cv2.LINE_AA)
        for t in trials:
            if t.state != optuna.trial.TrialState.COMPLETE:
                x, _ = px(t.number, lo)
                cv2.drawMarker(img, (x, y1 - 6), grey, cv2.MARKER_TILTED_CROSS, 8, 1)
        best = math.inf
        pts = []
        for i, v in sorted(done):
            best = min(best, v)
            pts.append(px(i, best))
        pts.append((x1, pts[-1][1]))
        for a, b in zip(pts[:-1], pts[1:]):
            cv2.line(img, a, (b[0], a[1]), red, 2, cv2.LINE_AA)
            cv2.line(img, (b[0], a[1]), b, red, 2, cv2.LINE_AA)
        for k in range(5):
            v = lo + k / 4 * (hi - lo)
            y = y1 - int(round(k / 4 * (y1 - y0)))
            cv2.line(img, (x0 - 4, y), (x0, y), black, 1)
            cv2.putText(img, f"{v:.4g}", (8, y + 4), font, 0.4, black, 1, cv2.LINE_AA)
        cv2.putText(img, f"best {min(vals):.5g}", (x1 - 150, y0 + 20), font, 0.45, red, 1, cv2.LINE_AA)
    for k in range(0, n, max(1, n // 10)):
        x = x0 + int(round((k + 0.5) / n * (x1 - x0)))
        cv2.putText(img, str(k), (x - 5, y1 + 18), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.putText(img, "trial", ((x0 + x1) // 2 - 15, y1 + 40), font, 0.45, black, 1, cv2.LINE_AA)
    # ---- importances
    bx0, by0, bx1 = 900, 60, W - 30
    cv2.putText(img, "parameter importance (fANOVA)", (680, by0 - 10), font, 0.45, black, 1, cv2.LINE_AA)
    if importances:
        items = sorted(importances.items(), key=lambda kv: -kv[1])[:12]
        row = min(34, (H - 100) // max(1, len(items)))
        top = max(v for _, v in items) or 1.0
        labels = option_labels([name for name, _ in items])
        for k, (name, v) in enumerate(items):
            y = by0 + 10 + k * row
            cv2.putText(img, labels[name], (680, y + row // 2 + 4), font, 0.4, black, 1, cv2.LINE_AA)
            w = int(round(v / top * (bx1 - bx0 - 50)))
            cv2.rectangle(img, (bx0, y + 4), (bx0 + max(w, 1), y + row - 4), blue, -1)
            cv2.putText(img, f"{v:.2f}", (bx0 + w + 5, y + row // 2 + 4), font, 0.4, black, 1, cv2.LINE_AA)
    else:
        cv2.putText(img, "(needs at least 3 completed trials)", (680, by0 + 30), font, 0.45, grey, 1, cv2.LINE_AA)
    return write_png(path, img)
