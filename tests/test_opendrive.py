"""``magail-sumo convert --opendrive``: the converted network as OpenDRIVE, read back by
netconvert."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"


def _lanes(net_file: Path) -> tuple[int, int, float]:
    """(edges, lanes, total lane length in m), junction-internal ones included."""
    import sumolib

    net = sumolib.net.readNet(str(net_file), withInternal=True)
    lanes = [ln for e in net.getEdges(withInternal=True) for ln in e.getLanes()]
    return len(net.getEdges(withInternal=True)), len(lanes), sum(ln.getLength() for ln in lanes)


@pytest.mark.sumo
def test_convert_opendrive_reads_back(tmp_path):
    from converters.sumo.opendrive import read_back

    out = tmp_path / "nets"
    proc = subprocess.run([sys.executable, "-m", "magail_sumo.cli.main", "convert", str(SCENE),
                           "--out", str(out), "--opendrive", "--no-baseline"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.returncode == 0, proc.stderr
    folder = out / "637f20cafde22ff8"
    xodr = folder / "637f20cafde22ff8.xodr"
    rep = json.loads((folder / "conversion.json").read_text())
    assert "637f20cafde22ff8.xodr" in rep["files"] and "opendrive" in rep["timings"]
    root = ET.parse(xodr).getroot()
    assert root.tag == "OpenDRIVE" and root.find("header") is not None
    assert len(root.findall("road")) > 50 and root.findall("junction")
    back = tmp_path / "back.net.xml"
    read_back(xodr, back, timeout_s=300)
    e0, l0, len0 = _lanes(folder / "637f20cafde22ff8.net.xml")
    e1, l1, len1 = _lanes(back)
    assert e1 == pytest.approx(e0, rel=0.1) and l1 == pytest.approx(l0, rel=0.1)
    assert len1 == pytest.approx(len0, rel=0.1)  # 5230 m vs 5505 m


@pytest.mark.sumo
def test_opendrive_off_by_default(tmp_path):
    from converters import load_scene
    from converters.sumo.scenario import ConvertOptions, convert_scene

    rep = convert_scene(load_scene(SCENE), tmp_path, ConvertOptions(baseline=False))
    assert rep.status == "ok" and not any(f.endswith(".xodr") for f in rep.files)
