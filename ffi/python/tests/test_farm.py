"""harmonizer.farm on a real dask.distributed LocalCluster (issue 22).

Two shots of the synthetic sequence (written by ``harmonize synth``) run in
chunks with a pre-roll on 2 worker processes of 1 thread each. Every output
must be written, by exactly one chunk, with the bytes ``harmonize run
--frames A-B --preroll N`` writes for that chunk; a worker killed in the
middle of a chunk (its process ends after writing 2 frames, on the chunk's
first attempt) has its chunk run again with complete outputs and no
temporary file left. The same job also runs as ``python -m harmonizer.farm
--scheduler tcp://127.0.0.1:PORT`` against a scheduler and two workers started
separately (``dask scheduler``, ``dask worker``), as on a real cluster. Needs
``dask[distributed]`` (scripts/setup-venv.sh installs it) and the release
build of ``harmonize`` beside the library.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

try:
    import distributed
except ImportError as e:  # a failure, not a skip: scripts/setup-venv.sh installs it
    raise ImportError("dask[distributed] is not installed: run scripts/setup-venv.sh (the farm tests need it)") from e

from harmonizer import _native, farm

CHUNK, PREROLL = 6, 4


def harmonize_cli() -> Path:
    """The ``harmonize`` binary built with the library this test loads."""
    lib = Path(_native.lib()._name)
    exe = lib.parent / "harmonize"
    if not exe.is_file():
        pytest.fail(f"{exe} not found: build it with `cargo build --release -p harmonizer-cli`")
    return exe


@pytest.fixture(scope="module")
def shots(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[str, int, int]]:
    """Two shots: ``a`` frames 1-20 (seed 1), ``b`` frames 5-18 (seed 2)."""
    root = tmp_path_factory.mktemp("shots")
    exe = harmonize_cli()
    out = {}
    for name, first, n, seed in (("a", 1, 20, 1), ("b", 5, 14, 2)):
        subprocess.run(
            [exe, "synth", "--out", root / name, "--frames", str(n), "--first", str(first), "--seed", str(seed), "--size", "64x36"],
            check=True,
            capture_output=True,
        )
        out[name] = (str(root / name / "input" / "shot.####.exr"), first, first + n - 1)
    return out


def cli_chunks(pattern: str, first: int, last: int, out: Path) -> dict[int, bytes]:
    """Every frame of the shot as the CLI writes it chunk by chunk."""
    exe = harmonize_cli()
    o = str(out / "shot.####.exr")
    for a in range(first, last + 1, CHUNK):
        b = min(a + CHUNK - 1, last)
        args = [exe, "run", pattern, "-o", o, "--backend", "classical", "--threads", "2", "--frames", f"{a}-{b}"]
        subprocess.run([*args, "--preroll", str(PREROLL)], check=True, capture_output=True)
    return {f: Path(farm.frame_path(o, f)).read_bytes() for f in range(first, last + 1)}


def assert_outputs_are_the_cli_chunks(shots: dict, out: Path, tmp_path: Path) -> None:
    """Each shot's output folder holds exactly its frames, with the bytes of
    the CLI's chunked run (no temporary left, nothing else)."""
    for name, (pattern, first, last) in shots.items():
        files = sorted(p.name for p in (out / name).iterdir())
        assert files == [f"shot.{f:04d}.exr" for f in range(first, last + 1)], files
        want = cli_chunks(pattern, first, last, tmp_path / f"cli-{name}")
        for f in range(first, last + 1):
            got = Path(farm.frame_path(str(out / name / "shot.####.exr"), f)).read_bytes()
            assert got == want[f], f"shot {name} frame {f} differs from harmonize run's chunk"


def test_two_shots_on_a_local_cluster_with_a_killed_worker(shots: dict, tmp_path: Path) -> None:
    out = tmp_path / "farm"
    job = [farm.shot_from_arg(f"{n}={p}", out, None) for n, (p, _, _) in shots.items()]
    settings = farm.Settings(backend="classical", library_threads=1, kill_first_attempt={"a#1": 2})
    seen: list[dict] = []
    result = farm.run_job(
        job,
        chunk=CHUNK,
        preroll=PREROLL,
        settings=settings,
        workers=2,
        threads_per_worker=1,
        summary=out / "summary.json",
        on_chunk=seen.append,
    )
    assert result["failed"] == [], result["failed"]
    assert result["workers"] == 2
    assert json.loads((out / "summary.json").read_text()) == result
    # a: 1-6, 7-12, 13-18, 19-20; b: 5-10, 11-16, 17-18.
    chunks = {(e["shot"], e["chunk"]): e for e in result["chunks"]}
    assert sorted(chunks) == [("a", 0), ("a", 1), ("a", 2), ("a", 3), ("b", 0), ("b", 1), ("b", 2)]
    # Each frame of each shot belongs to one chunk, written once in the summary.
    for name, (_, first, last) in shots.items():
        listed = [o for e in result["chunks"] if e["shot"] == name for o in e["outputs"]]
        want = [farm.frame_path(str(out / name / "shot.####.exr"), f) for f in range(first, last + 1)]
        assert sorted(listed) == want
    # The killed chunk ran twice (its first worker process ended after 2
    # frames), the others once; the pre-roll is fewer frames at a shot's start.
    assert chunks[("a", 1)]["attempts"] == 2, chunks[("a", 1)]
    assert all(e["attempts"] == 1 for k, e in chunks.items() if k != ("a", 1))
    assert chunks[("a", 0)]["preroll_frames"] == 0 and chunks[("a", 1)]["preroll_frames"] == PREROLL
    for e in result["chunks"]:
        assert e["worker"].startswith("tcp://") and e["seconds"] > 0 and e["pid"] != os.getpid()
        assert e["resets"] == ([{"frame": e["frames"][0] - min(PREROLL, e["frames"][0] - shots[e["shot"]][1]), "reason": "first_frame"}])
    # Outputs: exactly the chunks' frames, complete, no temporary left, and
    # the bytes of the CLI's chunked run.
    assert_outputs_are_the_cli_chunks(shots, out, tmp_path)
    assert result["stale_temporaries_removed"] >= 0


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[tuple[str, list[int]]]:
    """A ``dask scheduler`` on 127.0.0.1 (a free port) and two ``dask worker``
    processes of 1 process x 1 thread, each started as its own process in
    this Python environment; yields the scheduler's address and the
    workers' process ids. Every process is ended however the test ends."""
    dask = Path(sys.executable).parent / "dask"
    if not dask.is_file():
        pytest.fail(f"{dask} not found: the dask CLI comes with distributed (scripts/setup-venv.sh)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(farm.__file__).parents[1]), os.environ.get("PYTHONPATH", "")])}
    env["HARMONIZER_LIB"] = str(_native.lib()._name)  # the workers load the library this test loads
    logs = tmp_path / "dask-logs"
    logs.mkdir()
    procs: list[subprocess.Popen] = []

    def start(name: str, *args: str) -> subprocess.Popen:
        with open(logs / f"{name}.log", "wb") as log:
            p = subprocess.Popen([dask, *args], env=env, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        procs.append(p)
        return p

    try:
        sched_file = tmp_path / "scheduler.json"
        start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(sched_file))
        deadline = time.monotonic() + 30
        while not sched_file.is_file() or not sched_file.read_text().strip():
            assert procs[0].poll() is None, (logs / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler did not start in 30 s"
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for i in range(2):
            opts = ["--nworkers", "1", "--nthreads", "1", "--no-dashboard", "--name", f"w{i}", "--local-directory", str(tmp_path / f"dask-w{i}")]
            start(f"worker{i}", "worker", address, *opts)
        with distributed.Client(address, timeout=30) as client:
            client.wait_for_workers(2, timeout=60)
            pids = list(client.run(os.getpid).values())
        yield address, pids
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def test_two_shots_on_a_separately_started_scheduler(shots: dict, tmp_path: Path, dask_cluster: tuple[str, list[int]]) -> None:
    """``harmonize-farm --scheduler tcp://HOST:PORT`` (as ``python -m
    harmonizer.farm``, in its own process) on a scheduler and two workers
    it did not start."""
    address, worker_pids = dask_cluster
    assert address.startswith("tcp://127.0.0.1:")
    out = tmp_path / "farm"
    args = [f"{n}={p}" for n, (p, _, _) in shots.items()]
    opts = ["-o", str(out), "--scheduler", address, "--backend", "classical", "--chunk", str(CHUNK), "--preroll", str(PREROLL)]
    cmd = [sys.executable, "-m", "harmonizer.farm", *args, *opts]
    env = {**os.environ, "PYTHONPATH": str(Path(farm.__file__).parents[1])}
    r = subprocess.run(cmd, check=False, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((out / "farm-summary.json").read_text())
    assert summary["scheduler"] == address and summary["workers"] == 2, summary
    assert summary["failed"] == [] and summary["chunk"] == CHUNK and summary["preroll"] == PREROLL
    chunks = {(e["shot"], e["chunk"]): e for e in summary["chunks"]}
    assert sorted(chunks) == [("a", 0), ("a", 1), ("a", 2), ("a", 3), ("b", 0), ("b", 1), ("b", 2)]
    # The tasks ran in the two worker processes (not in the driver), both used.
    assert {e["pid"] for e in summary["chunks"]} == set(worker_pids), (summary["chunks"], worker_pids)
    assert all(e["attempts"] == 1 and e["worker"].startswith("tcp://127.0.0.1:") for e in summary["chunks"])
    assert summary["frames_written"] == sum(last - first + 1 for _, first, last in shots.values())
    # Every output written once (one chunk lists it), nothing else in the
    # folders, and the bytes of the CLI's chunked run.
    for name, (_, first, last) in shots.items():
        listed = sorted(o for e in summary["chunks"] if e["shot"] == name for o in e["outputs"])
        assert listed == [farm.frame_path(str(out / name / "shot.####.exr"), f) for f in range(first, last + 1)]
    assert_outputs_are_the_cli_chunks(shots, out, tmp_path)


def test_the_command_line(shots: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pattern, first, last = shots["b"]
    out = tmp_path / "cli"
    rc = farm.main([pattern, "-o", str(out), "--backend", "classical", "--chunk", "7", "--preroll", "2", "--workers", "1"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert f"{last - first + 1} frame(s) of 1 shot(s) in 2 chunk(s) on 1 worker(s)" in text, text
    summary = json.loads((out / "farm-summary.json").read_text())
    assert [e["frames"] for e in summary["chunks"]] == [[5, 11], [12, 18]]
    assert [e["preroll_frames"] for e in summary["chunks"]] == [0, 2]
    # Two shots of one name are refused before anything runs.
    rc = farm.main([pattern, pattern, "-o", str(tmp_path / "dup")])
    assert rc == 2 and "named ['shot'] twice" in capsys.readouterr().err


def test_run_sequence_reports_stops_and_reraises(shots: dict, tmp_path: Path, device) -> None:
    """Session.run_sequence: the frames' reports (pre-roll marked), a
    callback returning False cancels, one that raises has its exception
    re-raised; a pre-roll without frames is refused."""
    import harmonizer as hz

    pattern = shots["a"][0]
    out = str(tmp_path / "o.####.exr")
    with hz.Session(device, backend="classical") as s:
        reports = s.run_sequence(pattern, out, frames=(5, 7), preroll=3, report=tmp_path / "r.json")
        assert [(r["frame"], r["preroll"]) for r in reports] == [(2, True), (3, True), (4, True), (5, False), (6, False), (7, False)]
        assert json.loads((tmp_path / "r.json").read_text())["summary"]["preroll_frames"] == 3
        assert s.last_report["frame_index"] == 7
        with pytest.raises(hz.CancelledError, match="after frame 8"):
            s.run_sequence(pattern, out, frames="8-10", on_frame=lambda r: False)
        assert Path(farm.frame_path(out, 8)).exists() and not Path(farm.frame_path(out, 9)).exists()

        def boom(r: dict) -> None:
            raise KeyError("from the callback")

        with pytest.raises(KeyError, match="from the callback"):
            s.run_sequence(pattern, out, frames="11-12", on_frame=boom)
        with pytest.raises(hz.InvalidArgumentError, match="--preroll needs --frames"):
            s.run_sequence(pattern, out, preroll=2)


def test_several_insert_indices_reach_the_library(shots: dict, tmp_path: Path, device, capsys: pytest.CaptureFixture[str]) -> None:
    """``run_sequence(insert_index=[3, 5])`` and ``harmonize-farm
    --insert-index 3,5`` pass every index to the library (its checks and
    its messages name them); one index in a list is the single index."""
    import harmonizer as hz

    pattern = shots["a"][0]
    out = str(tmp_path / "o.####.exr")
    with hz.Session(device, backend="classical") as s:
        with pytest.raises(hz.InvalidArgumentError, match="options.insert_indices: 3 is named twice"):
            s.run_sequence(pattern, out, frames=(1, 1), insert_index=[3, 3])
        # These frames have no Object Index: the message names what was asked.
        with pytest.raises(hz.HarmonizerError, match="--insert-index 3,5"):
            s.run_sequence(pattern, out, frames=(1, 1), layout="blender", insert_index=(3, 5))
        with pytest.raises(hz.HarmonizerError, match="--insert-index 3[^,]"):
            s.run_sequence(pattern, out, frames=(1, 1), layout="blender", insert_index=[3])
    assert not Path(farm.frame_path(out, 1)).exists()
    rc = farm.main([pattern, "-o", str(tmp_path / "farm"), "--backend", "classical", "--insert-index", "3,0", "--workers", "1", "--chunk", "20", "--frames", "1-2", "--quiet"])
    assert rc == 1 and "0 is not above 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        farm.main([pattern, "-o", str(tmp_path / "farm"), "--insert-index", "3,x"])
