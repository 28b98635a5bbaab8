"""``harmonize-farm``: shots and long sequences over a Dask cluster, in
contiguous chunks with a pre-roll (issue 22).

The enhancer is causal and stateful, so a sequence cannot be scattered frame
by frame. Each shot is cut into contiguous chunks of ``chunk`` frames; a
chunk ``A-B`` first processes the ``preroll`` frames before ``A`` without
writing them (its temporal state is then close to that of a sequential run)
and writes ``A..B``. Every chunk is one task on a ``dask.distributed``
cluster (a ``LocalCluster`` by default, or ``--scheduler tcp://HOST:PORT``);
the task calls the library in process through this binding, with one
session of its own (:meth:`harmonizer.Session.run_sequence` for frame
patterns, ``usd_harmonizer`` for USD stages), so its outputs are the bytes
``harmonize run --frames A-B --preroll N`` writes.

Retries, without partial or duplicate outputs:

- every output file is written by the library to a temporary file in the
  output's folder and renamed over the output (atomic on POSIX): an output
  is complete or absent, never partial;
- chunks never share an output (checked before anything is submitted:
  every frame of every shot has one chunk and one output path, none of
  them an input);
- a failed chunk runs again from its pre-roll: a worker that dies (killed,
  out of memory) has its task rescheduled by the scheduler, an exception is
  retried ``retries`` times. The rerun writes every output of the chunk
  again with the same bytes (the run is deterministic), so the outputs an
  earlier attempt finished are overwritten identically and the ones it did
  not reach are written;
- the temporary files of a killed attempt (``<output>.tmp-<pid>``;
  usd_harmonizer's ``.<name>.tmp<pid>.exr``) are removed when the job ends
  (counted in the summary).

The job summary (``--summary``, JSON) has, per chunk: shot, frames,
pre-roll frames, worker, host and process, seconds, attempts, resets and
warnings.

    harmonize-farm in/a/shot.####.exr in/b/shot.####.exr -o out/ \\
        --chunk 24 --preroll 4 --workers 2 --threads-per-worker 1
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ._api import parse_param

#: The pre-roll a chunk gets by default: the smallest of 0, 4, 8, 16 with
#: which every frame of chunks of 24 is at least 40 dB from the sequential
#: run's, on the 96-frame synthetic sequence with the classical and the
#: neural backend (docs/farm.md, cli/tests/cli.rs preroll::seams).
DEFAULT_PREROLL = 4
#: Frames per chunk by default.
DEFAULT_CHUNK = 24

_TOKEN = re.compile(r"(#+)|%0?(\d*)d|\$\{F(\d*)\}|\$F(\d*)|<F(\d*)>")
_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


class FarmError(Exception):
    """A job that cannot run as asked (bad shot, overlapping outputs, ...)."""


# -- frame patterns --------------------------------------------------------
def _token(pattern: str) -> tuple[re.Match[str], int]:
    m = _TOKEN.search(pattern)
    if m is None:
        raise FarmError(f"{pattern}: no frame token (####, %04d, $F4, ${{F4}} or <F4>)")
    width = len(m.group(1)) if m.group(1) else int(next((g for g in m.groups()[1:] if g), "1") or 1)
    return m, width


def frame_path(pattern: str, frame: int) -> str:
    """``pattern`` with its frame token replaced by ``frame`` (zero-padded)."""
    m, width = _token(pattern)
    num = f"-{str(-frame).zfill(max(width - 1, 0))}" if frame < 0 else str(frame).zfill(width)
    return pattern[: m.start()] + num + pattern[m.end() :]


def list_frames(pattern: str) -> list[int]:
    """The frame numbers of the files that exist for ``pattern``, sorted."""
    m, width = _token(pattern)
    head, tail = pattern[: m.start()], pattern[m.end() :]
    rx = re.compile(re.escape(head) + r"(-?\d+)" + re.escape(tail) + r"\Z")
    frames = set()
    for p in glob.glob(glob.escape(head) + "*" + glob.escape(tail)):
        mm = rx.match(p)
        if mm and len(mm.group(1).lstrip("-")) >= width:
            frames.add(int(mm.group(1)))
    return sorted(frames)


# -- the job -----------------------------------------------------------------
@dataclass
class Shot:
    """One sequence to process: a frame pattern, or a USD stage."""

    name: str
    #: Input frame pattern, or the USD stage.
    input: str
    #: Output frame pattern (frame patterns), or the output folder (stages:
    #: ``usd-harmonize --out-dir``).
    output: str
    #: Frames written, first..last (all exist).
    first: int
    last: int
    #: ``exr`` or ``usd``.
    kind: str = "exr"


@dataclass
class Chunk:
    """Frames ``first..last`` of a shot, after ``preroll`` frames."""

    shot: Shot
    index: int
    first: int
    last: int
    preroll: int

    @property
    def key(self) -> str:
        return f"{self.shot.name}#{self.index}"


@dataclass
class Settings:
    """What every task runs with."""

    backend: str = "auto"
    context_frames: int = 4
    #: Further session parameters by name.
    params: dict[str, Any] = field(default_factory=dict)
    #: Library threads per task (0 = one per core).
    library_threads: int = 1
    model: str | None = None
    #: Blender layout: the Object Index of the insert, or of several inserts
    #: (each harmonized by its own index), as ``harmonize run --insert-index``.
    insert_index: list[int] = field(default_factory=list)
    #: Folder for the attempt markers (the job's own scratch folder).
    scratch: str = ""
    #: Testing only: ``{chunk key: frames}`` makes the first attempt of that
    #: chunk end its worker process (``os._exit``) after writing that many
    #: frames, as a killed worker would.
    kill_first_attempt: dict[str, int] = field(default_factory=dict)


def shot_from_arg(arg: str, out_dir: Path, frames: tuple[int, int] | None) -> Shot:
    """A shot from ``[NAME=]PATTERN`` or ``[NAME=]STAGE.usd[a|c|z]``; its
    output goes to ``out_dir/NAME/``."""
    name, sep, path = arg.partition("=")
    if not sep:
        name, path = "", arg
    if path.lower().endswith(_USD_SUFFIXES):
        name = name or Path(path).stem
        if frames is None:
            try:
                from usd_harmonizer.settings import open_stage, resolve
            except ImportError as e:
                raise FarmError(f"{path}: a USD stage needs usd_harmonizer (pip install ./usd_plugin): {e}") from e
            info = resolve(open_stage(path), None, None, None, None)
            frames = (min(info.frames), max(info.frames))
        return Shot(name, str(path), str(out_dir / name), frames[0], frames[1], "usd")
    m, _ = _token(path)
    if not name:
        stem = os.path.basename(path[: m.start()]).rstrip("._-")
        name = stem or Path(path).parent.name
    existing = list_frames(path)
    if frames is None:
        if not existing:
            raise FarmError(f"shot {name}: no file matches {path}")
        frames = (existing[0], existing[-1])
    missing = sorted(set(range(frames[0], frames[1] + 1)) - set(existing))
    if missing:
        raise FarmError(f"shot {name}: {len(missing)} frame(s) missing, first {frame_path(path, missing[0])}")
    return Shot(name, path, str(out_dir / name / os.path.basename(path)), frames[0], frames[1], "exr")


def plan(shots: list[Shot], chunk: int, preroll: int) -> list[Chunk]:
    """Contiguous chunks of ``chunk`` frames per shot (the last may be
    shorter). Refuses two shots of one name, an output written twice and
    an output that is an input."""
    if chunk < 1 or preroll < 0:
        raise FarmError(f"chunk {chunk} and preroll {preroll}: expected chunk >= 1, preroll >= 0")
    names = [s.name for s in shots]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise FarmError(f"shots named {sorted(dup)} twice: name them, NAME=PATTERN")
    outputs: dict[str, str] = {}
    inputs: set[str] = set()
    for s in shots:
        if s.kind == "exr":
            inputs.update(os.path.realpath(frame_path(s.input, f)) for f in range(s.first, s.last + 1))
    chunks = []
    for s in shots:
        for i, a in enumerate(range(s.first, s.last + 1, chunk)):
            chunks.append(Chunk(s, i, a, min(a + chunk - 1, s.last), preroll))
        if s.kind != "exr":
            continue
        for f in range(s.first, s.last + 1):
            out = os.path.realpath(frame_path(s.output, f))
            if out in inputs:
                raise FarmError(f"shot {s.name} frame {f}: the output {out} is an input")
            if out in outputs:
                raise FarmError(f"shot {s.name} frame {f}: {out} is also the output of {outputs[out]}")
            outputs[out] = f"shot {s.name} frame {f}"
    return chunks


def _attempt(settings: Settings, chunk: Chunk) -> int:
    """Counts this attempt of ``chunk`` (a marker file per attempt in the
    job's scratch folder, made atomically), 1 for the first."""
    d = Path(settings.scratch) / "attempts"
    d.mkdir(parents=True, exist_ok=True)
    n = 1
    while True:
        try:
            fd = os.open(d / f"{chunk.key}.{n}", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            os.close(fd)
            return n
        except FileExistsError:
            n += 1


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def run_chunk(chunk: Chunk, settings: Settings) -> dict[str, Any]:
    """Runs one chunk in this process (the task of a worker): one device and
    one session, the library reading and writing the files. Returns the
    chunk's summary entry."""
    from . import Device, Session

    attempt = _attempt(settings, chunk)
    kill_after = settings.kill_first_attempt.get(chunk.key) if attempt == 1 else None
    t0 = time.perf_counter()
    frames: list[dict[str, Any]] = []
    s = chunk.shot
    if s.kind == "usd":
        frames = _run_usd_chunk(chunk, settings, kill_after)
    else:
        params = dict(settings.params)
        params.setdefault("backend", settings.backend)
        params.setdefault("context_frames", settings.context_frames)

        def on_frame(r: dict[str, Any]) -> None:
            frames.append(r)
            if kill_after is not None and sum(not f["preroll"] for f in frames) >= kill_after:
                os._exit(17)  # the worker process dies mid-chunk (testing)

        with Device(threads=settings.library_threads, model=settings.model) as device:
            with Session(device, **params) as session:
                frames = session.run_sequence(
                    s.input,
                    s.output,
                    frames=(chunk.first, chunk.last),
                    preroll=chunk.preroll,
                    insert_index=settings.insert_index or None,
                    render_hints=True,
                    on_frame=on_frame,
                )
    written = [f for f in frames if not f["preroll"]]
    return {
        "shot": s.name,
        "chunk": chunk.index,
        "frames": [chunk.first, chunk.last],
        # Frames, not files: a USD stage writes one file per product and frame.
        "written": len({f["frame"] for f in written}),
        "preroll_frames": len({f["frame"] for f in frames if f["preroll"]}),
        "worker": _worker_name(),
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "attempt": attempt,
        "seconds": round(time.perf_counter() - t0, 3),
        "resets": [{"frame": f["frame"], "reason": f["reset"]} for f in frames if f.get("reset")],
        # Every file written (USD: each product's).
        "warnings": [f"frame {f['frame']}: {w}" for f in frames for w in f.get("warnings", [])],
        "outputs": [f["output"] for f in written],
    }


def _run_usd_chunk(chunk: Chunk, settings: Settings, kill_after: int | None) -> list[dict[str, Any]]:
    from usd_harmonizer.process import Options
    from usd_harmonizer.run import run_stage

    s = chunk.shot
    frames = list(range(chunk.first, chunk.last + 1))
    params = {"context_frames": settings.context_frames, **settings.params}
    options = Options(
        backend=settings.backend,
        params=params,
        out_dir=Path(s.output),
        threads=settings.library_threads,
        model=settings.model,
    )
    seen = [0]

    def on_frame(done: int, total: int, prod: Any, frame: int) -> None:
        if kill_after is not None and done - chunk.preroll >= kill_after:
            os._exit(17)
        seen[0] = done

    summary = run_stage(s.input, frames=frames, options=options, write_layer_file=False, on_frame=on_frame, preroll=chunk.preroll)
    # Pre-roll frames per product (every product warms the same frames).
    per_product = summary.preroll_frames // max(len(summary.results), 1)
    out: list[dict[str, Any]] = [{"frame": chunk.first - per_product + i, "preroll": True, "reset": None} for i in range(per_product)]
    for _prod, results in summary.results.values():
        for r in results:
            out.append({"frame": r.frame, "preroll": False, "reset": r.reset, "warnings": r.warnings, "output": str(r.output)})
    return out


def _remove_stale_temporaries(shots: list[Shot]) -> int:
    """Removes the temporary files a killed attempt left: the library's
    ``<output>.tmp-<pid>``, usd_harmonizer's ``.<name>.tmp<pid>.exr``."""
    n = 0
    for s in shots:
        if s.kind == "exr":
            stale = [t for f in range(s.first, s.last + 1) for t in glob.glob(glob.escape(frame_path(s.output, f)) + ".tmp-*")]
        else:
            stale = [str(p) for p in Path(s.output).rglob(".*.tmp*") if p.is_file()]
        for t in stale:
            os.remove(t)
            n += 1
    return n


class Progress:
    """A bar over chunks and frames on a terminal (stderr), else nothing."""

    def __init__(self, chunks: int, frames: int, enabled: bool) -> None:
        self.chunks, self.frames, self.enabled = chunks, frames, enabled
        self.done_chunks = self.done_frames = 0
        self.t0 = time.monotonic()

    def update(self, entry: dict[str, Any]) -> None:
        self.done_chunks += 1
        self.done_frames += entry.get("written", 0)
        if not self.enabled:
            return
        n = 30
        fill = n * self.done_frames // max(self.frames, 1)
        sys.stderr.write(
            f"\r[{'#' * fill}{'.' * (n - fill)}] chunks {self.done_chunks}/{self.chunks} "
            f"frames {self.done_frames}/{self.frames}  {time.monotonic() - self.t0:.1f}s"
        )
        if self.done_chunks == self.chunks:
            sys.stderr.write("\n")
        sys.stderr.flush()


def run_job(
    shots: list[Shot],
    *,
    chunk: int = DEFAULT_CHUNK,
    preroll: int = DEFAULT_PREROLL,
    settings: Settings | None = None,
    scheduler: str | None = None,
    workers: int = 2,
    threads_per_worker: int = 1,
    retries: int = 2,
    summary: str | os.PathLike[str] | None = None,
    progress: bool = False,
    on_chunk: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Runs every chunk of ``shots`` on a Dask cluster (a ``LocalCluster``
    of ``workers`` processes with ``threads_per_worker`` threads, or the
    scheduler at ``scheduler``) and returns the job summary (also written
    to ``summary``). Failed chunks are listed under ``"failed"``."""
    from distributed import Client, LocalCluster, as_completed

    settings = settings or Settings()
    chunks = plan(shots, chunk, preroll)
    scratch = Path(settings.scratch) if settings.scratch else None
    if scratch is None:
        import tempfile

        scratch = Path(tempfile.mkdtemp(prefix="harmonize-farm-"))
        settings.scratch = str(scratch)
    t0 = time.perf_counter()
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=None,
        )
    entries: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    try:
        with Client(cluster if cluster is not None else scheduler) as client:
            n_workers = len(client.scheduler_info().get("workers", {}))
            futures = {
                client.submit(run_chunk, c, settings, key=f"harmonize-{c.key}-{os.getpid()}-{id(settings)}", retries=retries, pure=False): c
                for c in chunks
            }
            bar = Progress(len(chunks), sum(s.last - s.first + 1 for s in shots), progress)
            for fut in as_completed(futures):
                c = futures[fut]
                try:
                    entry = fut.result()
                except Exception as e:  # noqa: BLE001 (reported per chunk)
                    failed.append({"shot": c.shot.name, "chunk": c.index, "frames": [c.first, c.last], "error": f"{type(e).__name__}: {e}"})
                    continue
                entries.append(entry)
                bar.update(entry)
                if on_chunk:
                    on_chunk(entry)
    finally:
        if cluster is not None:
            cluster.close()
    stale = _remove_stale_temporaries(shots)
    attempts_dir = scratch / "attempts"
    attempts: dict[str, int] = {}
    if attempts_dir.is_dir():
        for p in attempts_dir.iterdir():
            key, _, _n = p.name.rpartition(".")
            attempts[key] = attempts.get(key, 0) + 1
    for e in entries:
        e["attempts"] = attempts.get(f"{e['shot']}#{e['chunk']}", 1)
    entries.sort(key=lambda e: ([s.name for s in shots].index(e["shot"]), e["chunk"]))
    from . import version

    result = {
        "version": version(),
        "scheduler": scheduler or "LocalCluster",
        "workers": n_workers,
        "threads_per_worker": threads_per_worker if scheduler is None else None,
        "library_threads": settings.library_threads,
        "chunk": chunk,
        "preroll": preroll,
        "backend": settings.backend,
        "shots": [asdict(s) for s in shots],
        "chunks": entries,
        "failed": failed,
        "frames_written": sum(e["written"] for e in entries),
        "preroll_frames": sum(e["preroll_frames"] for e in entries),
        "stale_temporaries_removed": stale,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    if summary is not None:
        tmp = f"{os.fspath(summary)}.tmp-{os.getpid()}"
        Path(summary).parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "w") as f:
            json.dump(result, f, indent=2)
        os.replace(tmp, summary)
    return result


# -- command line -------------------------------------------------------------
def _frames(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(-?\d+)\s*-\s*(-?\d+)\s*", text)
    if not m or int(m.group(2)) < int(m.group(1)):
        raise argparse.ArgumentTypeError(f"{text!r}: expected A-B with A <= B")
    return int(m.group(1)), int(m.group(2))


def _indices(text: str) -> list[int]:
    """``N`` or ``N,N,...`` (``--insert-index``); the library checks the values."""
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not N or N,N,... (integers)") from None


def add_cmdline_args(parser: argparse.ArgumentParser) -> None:
    """The farm's options (shared with tools that wrap it)."""
    parser.add_argument("shots", nargs="+", metavar="SHOT", help="[NAME=]PATTERN (frame files) or [NAME=]STAGE.usd")
    parser.add_argument("-o", "--out-dir", type=Path, required=True, help="outputs go to OUT_DIR/NAME/")
    parser.add_argument("--frames", type=_frames, metavar="A-B", help="frames of every shot (default: all)")
    parser.add_argument("--chunk", type=int, default=DEFAULT_CHUNK, help=f"frames per chunk (default {DEFAULT_CHUNK})")
    parser.add_argument(
        "--preroll",
        type=int,
        default=DEFAULT_PREROLL,
        help=f"frames before each chunk processed and not written (default {DEFAULT_PREROLL})",
    )
    parser.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler (default: a LocalCluster)")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    parser.add_argument("--threads-per-worker", type=int, default=1, help="LocalCluster threads per worker (default 1)")
    parser.add_argument("--threads", type=int, default=1, help="library threads per task (default 1; 0 = all cores)")
    parser.add_argument("--retries", type=int, default=2, help="retries of a chunk that raised (a killed worker's chunk is rescheduled anyway)")
    parser.add_argument("--backend", default="auto", choices=["auto", "neural", "classical", "bypass"])
    parser.add_argument("--context", type=int, default=4, help="previous enhanced frames used (default 4, as harmonize run)")
    parser.add_argument("--model", help="ONNX model file (default: the embedded one)")
    parser.add_argument(
        "--insert-index",
        type=_indices,
        default=[],
        metavar="N[,N...]",
        help="Blender files: the Object Index of the insert, or of several inserts (each harmonized on its own)",
    )
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="any session parameter (repeatable)")
    parser.add_argument("--summary", type=Path, help="job summary JSON (default OUT_DIR/farm-summary.json)")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``harmonize-farm``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="harmonize-farm", description=__doc__.split("\n")[0].split(": ", 1)[1])
    add_cmdline_args(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary line")
    args = parser.parse_args(argv)
    params = {}
    for s in args.set:
        k, sep, v = s.partition("=")
        if not sep:
            print(f"harmonize-farm: error: --set {s!r}: expected NAME=VALUE", file=sys.stderr)
            return 2
        params[k.strip()] = parse_param(v.strip())
    try:
        shots = [shot_from_arg(a, args.out_dir, args.frames) for a in args.shots]
        settings = Settings(
            backend=args.backend,
            context_frames=args.context,
            params=params,
            library_threads=args.threads,
            model=args.model,
            insert_index=args.insert_index,
        )
        summary_path = args.summary or args.out_dir / "farm-summary.json"
        result = run_job(
            shots,
            chunk=args.chunk,
            preroll=args.preroll,
            settings=settings,
            scheduler=args.scheduler,
            workers=args.workers,
            threads_per_worker=args.threads_per_worker,
            retries=args.retries,
            summary=summary_path,
            progress=not args.quiet and sys.stderr.isatty(),
        )
    except FarmError as e:
        print(f"harmonize-farm: error: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        retried = sum(1 for e in result["chunks"] if e["attempts"] > 1)
        print(
            f"harmonize-farm: {result['frames_written']} frame(s) of {len(shots)} shot(s) in "
            f"{len(result['chunks'])} chunk(s) on {result['workers']} worker(s), {result['seconds']:.1f} s; "
            f"pre-roll frames {result['preroll_frames']}; chunks retried {retried}; summary {summary_path}"
        )
    for f in result["failed"]:
        print(f"harmonize-farm: chunk {f['shot']}#{f['chunk']} {f['frames'][0]}-{f['frames'][1]} failed: {f['error']}", file=sys.stderr)
    return 1 if result["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
