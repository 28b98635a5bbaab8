"""``usd-harmonize --frames A-B --preroll N`` (issue 22): a chunk of the
rendered shot (frames 1001-1006) warmed by the frames before it, which are
processed and not written, comes out as the sequential run's frames (here
the pre-roll reaches the shot's first frame, so exactly), where the same
chunk started cold differs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from usd_harmonizer.cli import main
from usd_harmonizer.exrio import read_exr

# `stabilize_all`: every pixel carries temporal state (the defaults leave
# this clean shot and its correctly lit insert as rendered).
COMMON = ["--product", "beauty", "--backend", "classical", "--no-layer", "--param", "stabilize_all=true"]


def rgb(path: Path) -> np.ndarray:
    return read_exr(path, "out").stack(["R", "G", "B"])


def test_a_chunk_with_a_preroll_continues_the_sequential_run(
    shot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq, warm, cold = tmp_path / "seq", tmp_path / "warm", tmp_path / "cold"
    assert main([str(shot), *COMMON, "--out-dir", str(seq), "--quiet"]) == 0
    chunk = ["--frames", "1004-1006"]
    assert main([str(shot), *COMMON, *chunk, "--preroll", "3", "--out-dir", str(warm)]) == 0
    assert "pre-roll: 3 frame(s)" in capsys.readouterr().out
    assert main([str(shot), *COMMON, *chunk, "--out-dir", str(cold), "--quiet"]) == 0
    # Only the chunk's frames are written.
    names = sorted(p.name for p in (warm / "beauty").iterdir())
    assert names == [f"beauty.{f}.exr" for f in (1004, 1005, 1006)], names

    def err(d: Path) -> float:
        return max(float(np.abs(rgb(d / "beauty" / n) - rgb(seq / "beauty" / n)).max()) for n in names)

    e_warm, e_cold = err(warm), err(cold)
    print(f"chunk 1004-1006 against the sequential run, max error: pre-roll 3 {e_warm:.2e}, none {e_cold:.2e}")
    assert e_cold > 1e-3, e_cold  # the temporal state matters on this shot
    assert e_warm == 0.0, e_warm


def test_a_preroll_needs_frames(shot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(shot), *COMMON, "--preroll", "2", "--out-dir", str(tmp_path / "o")]) == 1
    assert "--preroll needs --frames" in capsys.readouterr().err


def test_harmonize_farm_runs_the_stage_in_chunks(shot: Path, tmp_path: Path) -> None:
    """harmonize-farm with the stage as a shot (a LocalCluster of 2 worker
    processes): each chunk's files are the bytes usd-harmonize writes for
    that chunk with the same pre-roll."""
    pytest.importorskip("distributed", reason="dask[distributed] is not in .venv-usd (tests/usd/run.sh installs it)")
    from usd_harmonizer import binding

    binding.load()  # puts the checkout's binding on sys.path when needed
    from harmonizer import farm

    out = tmp_path / "farm"
    rc = farm.main([f"shot={shot}", "-o", str(out), "--backend", "classical", "--chunk", "3", "--preroll", "2", "--quiet"])
    assert rc == 0
    summary = json.loads((out / "farm-summary.json").read_text())
    assert [c["frames"] for c in summary["chunks"]] == [[1001, 1003], [1004, 1006]]
    for a, b in ((1001, 1003), (1004, 1006)):
        ref = tmp_path / f"ref-{a}"
        args = [str(shot), "--backend", "classical", "--no-layer", "--quiet", "--out-dir", str(ref)]
        assert main([*args, "--frames", f"{a}-{b}", "--preroll", "2"]) == 0
        for f in sorted(ref.rglob("*.exr")):
            got = out / "shot" / f.relative_to(ref)
            assert got.read_bytes() == f.read_bytes(), got
