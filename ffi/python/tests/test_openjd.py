"""The OpenJD job template of docs/farm.md, run by the real ``openjd`` CLI
(issue 22).

``examples/farm/harmonize.openjd.yaml`` is the template docs/farm.md shows
(the two must be the same text), ``openjd check`` validates it and ``openjd
run`` runs its step on this machine over a small synthetic shot, chunk after
chunk with a pre-roll: every frame must have the bytes ``harmonize run
--frames A-B --preroll N`` writes for its chunk. Needs ``openjd-cli``
(scripts/setup-venv.sh installs it; a missing ``openjd`` fails, it does not
skip) and the release build of ``harmonize`` beside the library.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from harmonizer import _native, farm

ROOT = Path(__file__).resolve().parents[3]
TEMPLATE = ROOT / "examples" / "farm" / "harmonize.openjd.yaml"
FIRST, LAST, CHUNK, PREROLL = 5, 18, 6, 2  # chunks 5-10, 11-16, 17-18


def harmonize_cli() -> Path:
    exe = Path(_native.lib()._name).parent / "harmonize"
    if not exe.is_file():
        pytest.fail(f"{exe} not found: build it with `cargo build --release -p harmonizer-cli`")
    return exe


def openjd_cli() -> str:
    exe = Path(sys.executable).parent / "openjd"
    found = str(exe) if exe.is_file() else shutil.which("openjd")
    if found is None:
        pytest.fail("the openjd CLI is not installed: run scripts/setup-venv.sh (it installs openjd-cli)")
    return found


def test_the_doc_shows_the_template() -> None:
    blocks = re.findall(r"^```yaml\n(.*?)^```$", (ROOT / "docs" / "farm.md").read_text(), re.MULTILINE | re.DOTALL)
    assert TEMPLATE.read_text() in blocks, "docs/farm.md must show examples/farm/harmonize.openjd.yaml as it is"


def test_openjd_check_and_run_equal_the_cli_chunks(tmp_path: Path) -> None:
    openjd, exe = openjd_cli(), harmonize_cli()
    r = subprocess.run([openjd, "check", TEMPLATE], check=False, capture_output=True, text=True)
    assert r.returncode == 0 and "passes validation checks" in r.stdout, r.stdout + r.stderr

    n = LAST - FIRST + 1
    synth = [exe, "synth", "--out", tmp_path / "shot", "--frames", str(n), "--first", str(FIRST), "--size", "64x36", "--seed", "3"]
    subprocess.run(synth, check=True, capture_output=True)
    pattern = str(tmp_path / "shot" / "input" / "shot.####.exr")
    out = str(tmp_path / "openjd" / "shot.####.exr")
    params = {"Input": pattern, "Output": out, "First": FIRST, "Last": LAST, "Chunk": CHUNK, "Preroll": PREROLL, "Backend": "classical", "Threads": 1}
    cmd = [openjd, "run", TEMPLATE, "--step", "Harmonize", "--output", "json"]
    for k, v in params.items():
        cmd += ["-p", f"{k}={v}"]
    # The template calls `harmonize` from PATH, as on a farm host.
    env = {**os.environ, "PATH": os.pathsep.join([str(exe.parent), os.environ.get("PATH", "")])}
    r = subprocess.run(cmd, check=False, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    result = json.loads(r.stdout)
    assert result["status"] == "success" and result["chunks_run"] == 3, {k: v for k, v in result.items() if k != "logs"}
    log = [e.get("message", "") for e in result["logs"]]
    runs = [m.groups() for m in (re.match(r"harmonize: (\d+) frame\(s\) written to (.*); backend (\w+);", t) for t in log) if m]
    assert runs == [("6", out, "classical"), ("6", out, "classical"), ("2", out, "classical")], log
    # The first chunk starts the shot (nothing before it), the others pre-roll.
    assert sum(f"pre-roll: {PREROLL} frame(s) before the first" in m for m in log) == 2, log

    # The same chunks through harmonize run, and the bytes compared.
    cli = str(tmp_path / "cli" / "shot.####.exr")
    for a in range(FIRST, LAST + 1, CHUNK):
        b = min(a + CHUNK - 1, LAST)
        run = [exe, "run", pattern, "-o", cli, "--backend", "classical", "--threads", "2", "--frames", f"{a}-{b}", "--preroll", str(PREROLL)]
        subprocess.run(run, check=True, capture_output=True)
    files = sorted(p.name for p in (tmp_path / "openjd").iterdir())
    assert files == [f"shot.{f:04d}.exr" for f in range(FIRST, LAST + 1)], files
    for f in range(FIRST, LAST + 1):
        got, want = Path(farm.frame_path(out, f)).read_bytes(), Path(farm.frame_path(cli, f)).read_bytes()
        assert got == want, f"frame {f}: openjd's chunk differs from harmonize run's"
