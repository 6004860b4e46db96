"""The fuzz test's worker (tests/test_fuzz.py runs it in a child process under a memory limit).

Reads seed files, mutates each one many times and runs the library call a command would make on every
mutant, each under a time limit. Acceptable: the call returns, or raises CartoError (what the CLI prints as
one line with exit 2). Anything else is a finding. Prints one JSON line: counts per format and findings.
"""
import gzip
import json
import random
import shutil
import signal
import sys
import traceback
from pathlib import Path

from carto_cli.core.errors import CartoError

TIME_LIMIT_S = 20


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang()


def consume_recording(path):
    from carto_cli.commands.info import inspect_recording
    from carto_cli.io.sources.open import open_recording

    with open_recording(path) as rec:
        inspect_recording(rec)


def load_profile(path):
    from carto_cli.options import load_options

    load_options(path)


def load_carto(path):
    from carto_cli.io.map_file import load_map

    loaded = load_map(path)
    loaded.to_pose_graph()


def trajectory(path):
    from carto_cli.io.trajectory import read_trajectory

    read_trajectory(path)


def relations(path):
    from carto_cli.evaluation.metrics import read_relations

    read_relations(path)


def queries(path):
    from carto_cli.relocalization.queries import read_queries

    read_queries(path)


CALLS = {"recording": consume_recording, "profile": load_profile, "carto": load_carto,
         "trajectory": trajectory, "relations": relations, "queries": queries}


def mutate(data: bytes, rng: random.Random, text: bool) -> bytes:
    if not data:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
    b = bytearray(data)
    kind = rng.randrange(6 if text else 5)
    if kind == 0:  # truncation
        return bytes(b[:rng.randrange(len(b))])
    if kind == 1:  # byte flips
        for _ in range(rng.randrange(1, 9)):
            b[rng.randrange(len(b))] = rng.randrange(256)
        return bytes(b)
    if kind == 2:  # insertion
        at = rng.randrange(len(b) + 1)
        return bytes(b[:at]) + bytes(rng.randrange(256) for _ in range(rng.randrange(1, 33))) + bytes(b[at:])
    if kind == 3:  # a duplicated chunk
        i = rng.randrange(len(b))
        j = min(len(b), i + rng.randrange(1, 257))
        at = rng.randrange(len(b) + 1)
        return bytes(b[:at]) + bytes(b[i:j]) + bytes(b[at:])
    if kind == 4:  # a removed chunk
        i = rng.randrange(len(b))
        return bytes(b[:i]) + bytes(b[min(len(b), i + rng.randrange(1, 257)):])
    # well-formed but adversarial text: a number replaced by nan, inf, huge, negative or zero
    words = data.decode("utf-8", "replace").split(" ")
    for _ in range(rng.randrange(1, 6)):
        k = rng.randrange(len(words))
        words[k] = rng.choice(["nan", "inf", "-inf", "1e308", "-1", "0", "1e-320", "99999999999"])
    return " ".join(words).encode()


def main():
    seeds_dir, out_dir, per_seed, seed = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    seeds = json.loads((seeds_dir / "seeds.json").read_text())
    rng = random.Random(seed)
    signal.signal(signal.SIGALRM, _alarm)
    counts, findings = {}, []
    if per_seed == 0:  # the seeds themselves must be read without complaint
        for entry in seeds:
            try:
                CALLS[entry["kind"]](seeds_dir / entry["path"])
            except BaseException as e:
                findings.append({"input": entry["path"], "kind": entry["kind"], "error": f"seed refused: {e}"})
        print(json.dumps({"counts": {}, "findings": findings}))
        return
    for entry in seeds:
        src = seeds_dir / entry["path"]
        kind, text = entry["kind"], entry.get("text", False)
        call = CALLS[kind]
        for i in range(per_seed):
            target = out_dir / f"{i}-{src.name}"
            if src.is_dir():  # a ROS2 bag: mutate its one storage file
                shutil.copytree(src, target)
                inner = next(p for p in target.iterdir() if p.suffix in (".db3", ".mcap"))
                inner.write_bytes(mutate(inner.read_bytes(), rng, False))
            elif src.suffix == ".gz":  # mutate the log inside, or the compressed bytes
                raw = gzip.decompress(src.read_bytes())
                target.write_bytes(gzip.compress(mutate(raw, rng, True)) if i % 2 else mutate(src.read_bytes(), rng, False))
            else:
                target.write_bytes(mutate(src.read_bytes(), rng, text))
            signal.alarm(TIME_LIMIT_S)
            try:
                call(target)
            except CartoError:
                pass
            except Hang:
                findings.append({"input": str(target), "kind": kind, "error": f"no answer in {TIME_LIMIT_S} s"})
            except BaseException as e:
                findings.append({"input": str(target), "kind": kind,
                                 "error": "".join(traceback.format_exception_only(type(e), e)).strip()[:300]})
            finally:
                signal.alarm(0)
            counts[entry["name"]] = counts.get(entry["name"], 0) + 1
            if not findings or findings[-1]["input"] != str(target):
                if target.is_dir():
                    shutil.rmtree(target)
                else:
                    target.unlink()
    print(json.dumps({"counts": counts, "findings": findings}))


if __name__ == "__main__":
    main()
