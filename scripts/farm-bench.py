#!/usr/bin/env python3
"""Throughput of harmonize-farm: 2 workers x 1 thread against 1 worker x 1
thread on a LocalCluster, the same job (issue 22).

Writes a synthetic sequence with ``harmonize synth`` (sway camera), then runs
it through ``harmonizer.farm.run_job`` once per configuration (library
threads 1 per task), each run into a fresh output folder, and prints one
JSON object: per configuration the wall time of the job (cluster start
included and separately the chunks' own seconds), frames per second, and the
machine's load average (``os.getloadavg``) before and after, since the
numbers mean little on a machine busy with other work.

    PYTHONPATH=ffi/python .venv/bin/python scripts/farm-bench.py \\
        [--frames 96] [--size 640x360] [--chunk 24] [--preroll 4] [--backend classical]

Needs the release build (``cargo build --release -p harmonizer-ffi -p
harmonizer-cli``) and ``dask[distributed]`` (scripts/setup-venv.sh).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "ffi" / "python"))

from harmonizer import farm  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--chunk", type=int, default=24)
    ap.add_argument("--preroll", type=int, default=farm.DEFAULT_PREROLL)
    ap.add_argument("--backend", default="classical")
    ap.add_argument("--configs", default="1x1,2x1", help="WORKERSxTHREADS, comma separated")
    args = ap.parse_args()
    exe = Path(os.environ.get("HARMONIZE", ROOT / "target" / "release" / "harmonize"))
    os.environ.setdefault("HARMONIZER_LIB", str(ROOT / "target" / "release" / "libharmonizer.so"))
    tmp = Path(tempfile.mkdtemp(prefix="farm-bench-"))
    try:
        subprocess.run(
            [exe, "synth", "--out", tmp / "shot", "--frames", str(args.frames), "--size", args.size, "--camera", "sway"],
            check=True,
            capture_output=True,
        )
        pattern = str(tmp / "shot" / "input" / "shot.####.exr")
        runs = []
        for cfg in args.configs.split(","):
            w, t = (int(x) for x in cfg.split("x"))
            out = tmp / f"out-{cfg}"
            shots = [farm.shot_from_arg(f"shot={pattern}", out, None)]
            load_before = os.getloadavg()
            t0 = time.perf_counter()
            r = farm.run_job(
                shots,
                chunk=args.chunk,
                preroll=args.preroll,
                settings=farm.Settings(backend=args.backend, library_threads=1),
                workers=w,
                threads_per_worker=t,
            )
            wall = time.perf_counter() - t0
            if r["failed"]:
                print(json.dumps(r["failed"], indent=2), file=sys.stderr)
                return 1
            runs.append(
                {
                    "workers": w,
                    "threads_per_worker": t,
                    "wall_s": round(wall, 2),
                    "chunk_seconds_sum": round(sum(e["seconds"] for e in r["chunks"]), 2),
                    "frames_per_s": round(r["frames_written"] / wall, 2),
                    "load_before": [round(x, 2) for x in load_before],
                    "load_after": [round(x, 2) for x in os.getloadavg()],
                }
            )
            shutil.rmtree(out)
        base = runs[0]["wall_s"]
        for r in runs:
            r["speedup"] = round(base / r["wall_s"], 2)
        print(
            json.dumps(
                {
                    "frames": args.frames,
                    "size": args.size,
                    "chunk": args.chunk,
                    "preroll": args.preroll,
                    "backend": args.backend,
                    "cpus": os.cpu_count(),
                    "runs": runs,
                },
                indent=2,
            )
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
