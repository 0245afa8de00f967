"""The scenarios shipped in networks/ open in SUMO as they are and meet the quality bars."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from conftest import ROOT

BUNDLES = sorted(p for p in (ROOT / "networks").iterdir() if p.is_dir())


def test_a_bundle_is_shipped():
    assert [b.name for b in BUNDLES] == ["637f20cafde22ff8"]


@pytest.mark.sumo
@pytest.mark.parametrize("bundle", BUNDLES, ids=lambda p: p.name)
def test_bundle_runs_in_sumo_and_meets_bars(bundle):
    report = json.loads((bundle / "conversion.json").read_text())
    assert report["status"] == "ok"
    for name in report["files"]:
        assert (bundle / name).is_file(), name
    q = report["quality"]
    assert q["on_network_rate"] >= 0.98 and q["route_rate"] >= 0.95
    assert q["signal_fidelity"] is None or q["signal_fidelity"] >= 0.99
    sumo = shutil.which("sumo")
    assert sumo, "eclipse-sumo provides the sumo binary"
    out = subprocess.run([sumo, "-c", f"{bundle.name}.sumocfg", "--no-step-log", "true"],
                         cwd=bundle, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "Error" not in out.stderr
