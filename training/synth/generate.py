"""Renders many training scenes, resumably: finished scenes are skipped.

    python -m training.synth.generate --out training/data --scenes 0:400

With ``--train-streams recon --frames 16`` the training scenes are longer and
render only the reconstruction stream (the one the network is run on), about
twice as many frames an hour; held-out scenes keep every stream. With
``--train-samples 16`` their clean renders take 16 samples (through OIDN, as
every clean render) instead of ``--samples``; held-out scenes keep
``--samples``.

Each scene runs in its own bpy process (``render_scene.py``) so a crash or a
leak cannot take the whole run down; a scene that fails is recorded in
``<out>/failed/scene_<id>.txt`` and skipped on the next run unless
``--retry-failed``. The split (train/test) is decided by scene id. Safe to stop
at any moment (Ctrl-C, ``kill <pid>``: the scene being rendered is ended too
and redone on the next run): a scene appears only when complete.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

TRAINING_DIR = Path(__file__).resolve().parent.parent
REPO = TRAINING_DIR.parent
DEFAULT_BPY_PYTHON = REPO / ".venv-bpy" / "bin" / "python"


def scene_dir(out: Path, scene_id: int, test_every: int) -> Path:
    split = "test" if scene_id % test_every == test_every - 1 else "train"
    return out / split / f"scene_{scene_id:06d}"


#: Exit codes of a render stopped from outside (SIGINT, SIGTERM): the scene
#: did not fail. A kill (SIGKILL, also the kernel's when memory runs out)
#: still counts as a failure, so a scene that cannot fit is not retried forever.
STOP_SIGNALS = (-2, -15)


def parse_range(s: str) -> range:
    if ":" in s:
        a, b = s.split(":", 1)
        return range(int(a), int(b))
    return range(int(s), int(s) + 1)


def add_render_args(ap: argparse.ArgumentParser) -> None:
    """Options shared with the smoke test and ``render_scene``."""
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--samples", type=int, default=32, help="samples of the clean renders (OIDN-denoised)")
    ap.add_argument("--threads", type=int, default=2, help="Cycles threads per render")
    ap.add_argument("--seed", type=int, default=1, help="global seed (with the scene id, fixes a scene)")
    ap.add_argument("--test-every", type=int, default=10, help="scene ids = k*N-1 are held out as test")


_current: dict = {"child": None, "stopping": False}


def _stop(signum, frame) -> None:
    """SIGTERM/SIGINT: end the scene being rendered too (it is redone on resume)."""
    _current["stopping"] = True
    child = _current["child"]
    if child is not None and child.poll() is None:
        child.terminate()


def _run(cmd: list[str], timeout: float) -> tuple[int, str]:
    """Runs one render process (the one ``_stop`` ends): its exit code (-1
    when killed after ``timeout`` seconds) and its output."""
    child = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _current["child"] = child
    try:
        out, _ = child.communicate(timeout=timeout)
        rc = child.returncode
    except subprocess.TimeoutExpired:
        child.kill()
        out, _ = child.communicate()
        rc = -1
    _current["child"] = None
    return rc, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=TRAINING_DIR / "data")
    ap.add_argument("--scenes", default="0:400", help="scene id range a:b (b excluded) or one id")
    ap.add_argument("--bpy-python", type=Path, default=Path(os.environ.get("HZ_BPY_PYTHON", DEFAULT_BPY_PYTHON)))
    ap.add_argument("--retry-failed", action="store_true")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per scene before it is abandoned")
    ap.add_argument(
        "--backfill-context",
        action="store_true",
        help="render nothing new: give the training scenes in --scenes that lack ctx.npz their context views "
        "(about 10 s a scene; kept only where the scene rebuilds the same)",
    )
    ap.add_argument(
        "--train-streams",
        choices=("all", "recon"),
        default="all",
        help="recon: training scenes render only what the reconstruction stream needs (the clean frames and "
        "the context views, a third of the renders per frame); held-out scenes always render every stream",
    )
    ap.add_argument(
        "--train-samples",
        type=int,
        default=0,
        help="samples of the training scenes' clean renders (0: --samples); held-out scenes always take "
        "--samples. 16 against 32: 44.5 dB against a 128-sample render instead of 47.4, about 1 s less a "
        "render at 256x144",
    )
    add_render_args(ap)
    args = ap.parse_args(argv)
    if not args.bpy_python.exists():
        print(f"generate: bpy interpreter {args.bpy_python} not found (see training/README.md)", file=sys.stderr)
        return 2
    # Assets first (idempotent), in the bpy interpreter so the HDRI path is bpy's.
    r = subprocess.run([str(args.bpy_python), "-m", "training.synth.assets"], cwd=REPO)
    if r.returncode != 0:
        return r.returncode
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    if args.backfill_context:
        return backfill_context(args)
    failed_dir = args.out / "failed"
    ids = list(parse_range(args.scenes))
    done = skipped = failed = 0
    t0 = time.time()
    for sid in ids:
        d = scene_dir(args.out, sid, args.test_every)
        fail_note = failed_dir / f"scene_{sid:06d}.txt"
        if (d / "meta.json").exists():
            skipped += 1
            continue
        if fail_note.exists() and not args.retry_failed:
            skipped += 1
            continue
        d.parent.mkdir(parents=True, exist_ok=True)
        cmd = [
            str(args.bpy_python),
            "-m",
            "training.synth.render_scene",
            "--scene-id",
            str(sid),
            "--out",
            str(d),
            "--width",
            str(args.width),
            "--height",
            str(args.height),
            "--frames",
            str(args.frames),
            "--samples",
            str((args.train_samples or args.samples) if d.parent.name == "train" else args.samples),
            "--threads",
            str(args.threads),
            "--seed",
            str(args.seed),
            "--test-every",
            str(args.test_every),
            "--streams",
            args.train_streams if d.parent.name == "train" else "all",
        ]
        ts = time.time()
        rc, out = _run(cmd, args.timeout)
        tail = f"timed out after {args.timeout} s\n{out[-2000:]}" if rc == -1 else out[-3000:]
        if _current["stopping"]:
            print(f"[{time.strftime('%H:%M:%S')}] stopped during scene {sid}; rerun to resume", flush=True)
            return 130
        if rc in STOP_SIGNALS:
            # The render itself was stopped from outside (the machine
            # shutting down, someone freeing the cores): not the scene's
            # failure, so a rerun renders it again.
            print(
                f"[{time.strftime('%H:%M:%S')}] scene {sid}'s render was stopped (signal {-rc}); rerun to resume",
                flush=True,
            )
            return 130
        if rc == 0 and (d / "meta.json").exists():
            done += 1
            last = [ln for ln in out.splitlines() if ln.startswith("{")]
            print(
                f"[{time.strftime('%H:%M:%S')}] scene {sid} ok in {time.time() - ts:.0f}s {last[-1] if last else ''}",
                flush=True,
            )
            fail_note.unlink(missing_ok=True)
        else:
            failed += 1
            failed_dir.mkdir(parents=True, exist_ok=True)
            fail_note.write_text(f"exit {rc}\ncommand: {' '.join(cmd)}\n\n{tail}\n")
            print(f"[{time.strftime('%H:%M:%S')}] scene {sid} FAILED (exit {rc}), see {fail_note}", flush=True)
    summary = {
        "rendered": done,
        "skipped": skipped,
        "failed": failed,
        "seconds": round(time.time() - t0),
    }
    print("generate: " + json.dumps(summary), flush=True)
    return 0 if failed == 0 else 1


def backfill_context(args: argparse.Namespace) -> int:
    """``--backfill-context``: ``render_scene --context-only`` on each
    training scene of the range without ``ctx.npz``. A scene that does not
    rebuild the same is noted in ``failed/ctx_scene_<id>.txt`` and not
    tried again."""
    failed_dir = args.out / "failed"
    kept = rejected = 0
    t0 = time.time()
    for sid in parse_range(args.scenes):
        d = scene_dir(args.out, sid, args.test_every)
        note = failed_dir / f"ctx_scene_{sid:06d}.txt"
        if d.parent.name != "train" or not (d / "meta.json").exists() or (d / "ctx.npz").exists() or note.exists():
            continue
        cmd = [str(args.bpy_python), "-m", "training.synth.render_scene", "--scene-id", str(sid), "--out", str(d)]
        cmd += ["--threads", str(args.threads), "--context-only"]
        rc, out = _run(cmd, args.timeout)
        if _current["stopping"] or rc in STOP_SIGNALS:
            print(f"[{time.strftime('%H:%M:%S')}] stopped during the context views of scene {sid}", flush=True)
            return 130
        last = [ln for ln in out.splitlines() if ln.startswith("{")]
        if rc == 0:
            kept += 1
        else:
            rejected += 1
            failed_dir.mkdir(parents=True, exist_ok=True)
            note.write_text(f"exit {rc}\ncommand: {' '.join(cmd)}\n\n{out[-3000:]}\n")
        print(
            f"[{time.strftime('%H:%M:%S')}] scene {sid} context views {'kept' if rc == 0 else 'NOT kept'} "
            f"{last[-1] if last else ''}",
            flush=True,
        )
    summary = {"context_kept": kept, "context_rejected": rejected, "seconds": round(time.time() - t0)}
    print("generate: " + json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
