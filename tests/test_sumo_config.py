"""SUMO is started only with options the tool chose (magail_sumo/sim/sumo_config.py).

Crafted configurations carry every kind of SUMO output, a log, a TraCI port and files that make
SUMO write; real SUMO runs them (libsumo and the ``sumo`` binary) and nothing may appear
outside the output folder, no port may open, and the files SUMO must not read are refused.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from magail_sumo.inputs import InputFileError, read_json
from magail_sumo.sim.binaries import binary
from magail_sumo.sim.session import SessionConfig, SimulationError, SumoSession
from magail_sumo.sim.sumo_config import (OPTIONS_FILE, SumoConfigError, check_demand, option,
                                         read_config, template_table)

ROOT = Path(__file__).resolve().parents[1]
SID = "637f20cafde22ff8"
PORT = 45999

#: every kind of option a configuration could use to write, log or listen
HOSTILE_OPTIONS = {
    "tripinfo-output": "{out}/precious.txt", "fcd-output": "{out}/fcd.xml",
    "summary-output": "{out}/summary.xml", "netstate-dump": "{out}/netstate.xml",
    "vehroute-output": "{out}/vehroutes.xml", "statistic-output": "{out}/stats.xml",
    "log": "{out}/log.txt", "message-log": "{out}/messages.txt",
    "error-log": "{out}/errors.txt", "save-state.times": "1",
    "save-state.files": "{out}/state.xml", "save-configuration": "{out}/saved.sumocfg",
    "output-prefix": "{out}/prefix_", "remote-port": str(PORT),
    "device.rerouting.output": "{out}/weights.xml", "device.ssm.probability": "1",
    "device.ssm.file": "{out}/ssm.xml", "random": "true",
}


def _listening(port: int) -> bool:
    """Whether anything on this machine accepts TCP connections on ``port``."""
    for family, host in ((socket.AF_INET, "127.0.0.1"), (socket.AF_INET6, "::1")):
        with socket.socket(family) as s:
            s.settimeout(0.5)
            try:
                if s.connect_ex((host, port)) == 0:
                    return True
            except OSError:
                pass
    return False


def _listening_ports() -> set[int]:
    """Ports of every listening TCP socket of this machine (``/proc/net/tcp{,6}``)."""
    ports = set()
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()
            if cols[3] == "0A":  # TCP_LISTEN
                ports.add(int(cols[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.fixture()
def crafted(tmp_path):
    """(bundle folder, its hostile .sumocfg, the outside folder, the precious file)."""
    outside = tmp_path / "outside"
    outside.mkdir()
    precious = outside / "precious.txt"
    precious.write_text("keep me\n")
    bundle = tmp_path / "nets" / SID
    shutil.copytree(ROOT / "networks" / SID, bundle)
    cfg = bundle / f"{SID}.sumocfg"
    text = cfg.read_text()
    extra = "".join(f'  <{k} value="{v.format(out=outside)}"/>\n' for k, v in HOSTILE_OPTIONS.items())
    cfg.write_text(text.replace("</configuration>", f"  <output>\n{extra}  </output>\n"
                                "</configuration>"))
    return bundle, cfg, outside, precious


def _outside_intact(outside: Path, precious: Path) -> None:
    assert precious.read_text() == "keep me\n"
    assert sorted(p.name for p in outside.iterdir()) == ["precious.txt"]


@pytest.mark.sumo
def test_libsumo_session_of_a_hostile_config_writes_nothing_and_listens_nowhere(crafted):
    bundle, cfg, outside, precious = crafted
    before = sorted(p.name for p in bundle.iterdir())
    ports = _listening_ports()
    inputs = read_config(cfg)
    for name in HOSTILE_OPTIONS:
        assert any(d.startswith(option(name).name + " ") for d in inputs.dropped), name
    with SumoSession(cfg, config=SessionConfig(seed=1)) as sim:
        assert not _listening(PORT)
        assert _listening_ports() <= ports  # libsumo opened no port at all
        for _ in range(40):
            sim.step()
    _outside_intact(outside, precious)
    assert sorted(p.name for p in bundle.iterdir()) == before


@pytest.mark.sumo
def test_sumo_binary_run_of_a_hostile_config_writes_only_its_own_outputs(crafted, tmp_path):
    from magail_sumo.evaluation.traffic.sumo_outputs import run_sumo_outputs

    _, cfg, outside, precious = crafted
    out = tmp_path / "out"
    done = threading.Event()
    seen = []

    def watch():  # the port must never open while the run goes on
        while not done.is_set():
            seen.append(_listening(PORT))
            time.sleep(0.05)

    t = threading.Thread(target=watch)
    t.start()
    try:
        summary = run_sumo_outputs(cfg, out, seed=0)
    finally:
        done.set()
        t.join()
    assert not any(seen)
    assert summary.arrived > 0
    _outside_intact(outside, precious)
    assert sorted(p.name for p in out.iterdir()) == ["edgedata.xml", "statistics.xml",
                                                      "summary.xml", "tripinfo.xml"]


@pytest.mark.sumo
def test_additional_outputs_are_silenced_includes_followed(tmp_path):
    """An additional file's detectors and edge data (also through an ``<include>``, also a
    ``host:port`` 'file') run with their outputs to SUMO's null device."""
    bundle = tmp_path / SID
    shutil.copytree(ROOT / "networks" / SID, bundle)
    outside = tmp_path / "outside"
    outside.mkdir()
    sub = bundle / "sub"
    sub.mkdir()
    lanes = _lanes(bundle / f"{SID}.net.xml")
    lane = max((x for x in lanes if not x.startswith(":")), key=lanes.get)
    (sub / "inner.add.xml").write_text(
        f'<additional><edgeData id="inner" file="{outside}/inner.xml"/>'
        f'<e1Detector id="d1" lane="{lane}" pos="1" period="1" file="det.xml"/></additional>')
    (bundle / "outer.add.xml").write_text(
        '<additional xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
        'xsi:noNamespaceSchemaLocation="http://sumo.dlr.de/xsd/additional_file.xsd">'
        '<include href="sub/inner.add.xml"/>'
        f'<edgeData id="outer" file="{outside}/outer.xml"/>'
        '<laneData id="net" file="127.0.0.1:9"/></additional>')
    cfg = bundle / f"{SID}.sumocfg"
    cfg.write_text(cfg.read_text().replace(f"{SID}.tll.xml", f"{SID}.tll.xml,outer.add.xml"))
    inputs = read_config(cfg)
    notes = " | ".join(inputs.dropped)
    for what in ("edgeData 'outer'", "laneData 'net'", "edgeData 'inner'", "e1Detector 'd1'"):
        assert what in notes
    assert "-c" not in SumoSession(cfg).command()
    with SumoSession(cfg) as sim:
        for _ in range(20):
            sim.step()
        private = sim._private.name
        assert Path(private).is_dir()
    assert not Path(private).exists()  # the cleaned copies go with the session
    assert list(outside.iterdir()) == []
    assert not (sub / "det.xml").exists() and not (bundle / "det.xml").exists()


def _lanes(net: Path) -> dict[str, float]:
    import xml.etree.ElementTree as ET

    return {el.get("id"): float(el.get("length")) for el in ET.parse(net).getroot().iter("lane")}


@pytest.mark.parametrize("key", ["has.ssm.device", "has.toc.device", "device.ssm.file",
                                 "device.fcd.output"])
def test_device_params_that_write_are_refused(tmp_path, key):
    routes = tmp_path / "r.rou.xml"
    routes.write_text(f'<routes><vType id="t"><param key="{key}" value="x.xml"/></vType>'
                      '<vehicle id="v" type="t" depart="0"><route edges="a"/></vehicle></routes>')
    with pytest.raises(SumoConfigError, match=rf"r.rou.xml: vType 't' param '{key}'"):
        check_demand([routes])
    add = tmp_path / "a.add.xml"
    add.write_text(f'<additional><vType id="u"><param key="{key}" value="1"/></vType></additional>')
    net = ROOT / "networks" / SID / f"{SID}.net.xml"
    cfg = tmp_path / "c.sumocfg"
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<additional-files value="a.add.xml"/></configuration>')
    with pytest.raises(SumoConfigError, match=rf"a.add.xml: vType 'u' param '{key}'"):
        read_config(cfg)


def test_flat_layout_synonyms_gzip_and_any_name(tmp_path):
    """As SUMO's loader: options at any depth, synonyms, gzipped inputs, any file name."""
    import gzip

    src = ROOT / "networks" / SID
    (tmp_path / "n.net.xml.gz").write_bytes(gzip.compress((src / f"{SID}.net.xml").read_bytes()))
    shutil.copy(src / f"{SID}.rou.xml", tmp_path / "r.rou.xml")
    cfg = tmp_path / "run.sumo.cfg"
    cfg.write_text('<sumoConfiguration><net value="n.net.xml.gz"/><r v="r.rou.xml"/>'
                   '<begin value="3"/><verbose value="true"/><not-an-option value="1"/>'
                   "</sumoConfiguration>")
    inputs = read_config(cfg)
    assert inputs.net == (tmp_path / "n.net.xml.gz").absolute()
    assert inputs.routes == ((tmp_path / "r.rou.xml").absolute(),)
    assert inputs.options == (("begin", "3"),)
    assert "verbose (report)" in inputs.dropped
    assert "not-an-option (not an option of this SUMO)" in inputs.dropped
    ids = check_demand(inputs.routes)
    assert len(ids) > 5


def test_missing_and_odd_inputs_are_one_line(tmp_path):
    net = tmp_path / "n.net.xml"
    cfg = tmp_path / "c.sumocfg"
    cfg.write_text('<configuration><input><net-file value="n.net.xml"/>'
                   '<route-files value="gone.rou.xml"/></input></configuration>')
    with pytest.raises(SumoConfigError, match=r"c.sumocfg: net-file n.net.xml: not found$"):
        read_config(cfg)
    os.mkfifo(net)  # a FIFO would block SUMO forever
    t0 = time.monotonic()
    with pytest.raises(SumoConfigError, match=r"net-file n.net.xml: is a FIFO"):
        read_config(cfg)
    assert time.monotonic() - t0 < 5
    net.unlink()
    net.symlink_to("/dev/zero")
    with pytest.raises(SumoConfigError, match=r"net-file n.net.xml: is a character device"):
        read_config(cfg)
    net.unlink()
    shutil.copy(ROOT / "networks" / SID / f"{SID}.net.xml", net)
    with pytest.raises(SumoConfigError, match=r"c.sumocfg: route-files gone.rou.xml: not found"):
        read_config(cfg)
    (tmp_path / "z.sumocfg").symlink_to("/dev/zero")
    with pytest.raises(SumoConfigError, match=r"z.sumocfg: is a character device"):
        read_config(tmp_path / "z.sumocfg")
    with pytest.raises(SimulationError, match=r"z.sumocfg: is a character device"):
        SumoSession(tmp_path / "z.sumocfg").start()


def test_bundle_config_may_name_only_its_own_files(tmp_path):
    from converters.sumo.bundle import BundleError, BundleLayout

    bundle = tmp_path / SID
    shutil.copytree(ROOT / "networks" / SID, bundle)
    elsewhere = tmp_path / "other.rou.xml"
    shutil.copy(bundle / f"{SID}.rou.xml", elsewhere)
    cfg = bundle / f"{SID}.sumocfg"
    cfg.write_text(cfg.read_text().replace(f"{SID}.rou.xml", str(elsewhere)))
    with pytest.raises(BundleError, match="not one of its bundle's own files"):
        BundleLayout.of(bundle, SID).sumo_inputs()


def test_option_table_matches_the_installed_sumo(tmp_path):
    """``sumo_options.json`` is the installed ``sumo``'s option table (regenerate it with
    ``python -m magail_sumo.sim.sumo_config`` after a SUMO upgrade)."""
    template = tmp_path / "t.xml"
    subprocess.run([binary("sumo"), "--save-template", str(template)], check=True,
                   capture_output=True)
    shipped = read_json(OPTIONS_FILE)
    assert shipped["options"] == template_table(template.read_text())


def test_read_json_guards(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputFileError, match=r"deep.json: JSON nested deeper than 64 levels"):
        read_json(deep)
    with pytest.raises(InputFileError, match=r"is a character device"):
        read_json("/dev/zero")
    big = tmp_path / "big.json"
    big.write_text("[" + "0," * 1000 + "0]")
    with pytest.raises(InputFileError, match=r"big.json: is 1.96 KiB, more than the 1 KiB"):
        read_json(big, limit=1024)


@pytest.mark.sumo
def test_traffic_light_detector_files_are_silenced_or_refused(tmp_path):
    """An actuated program's ``<param key="file">`` makes SUMO write detector output: in an
    additional file it goes to NUL (the run works, nothing written); in a network (not
    rewritten) it is refused in one line."""
    bundle = tmp_path / SID
    shutil.copytree(ROOT / "networks" / SID, bundle)
    outside = tmp_path / "outside"
    outside.mkdir()
    tll = bundle / f"{SID}.tll.xml"
    tll.write_text(tll.read_text().replace(
        'type="static" programID="womd" offset="0">',
        f'type="actuated" programID="womd" offset="0"><param key="file" '
        f'value="{outside}/det.xml"/><param key="freq" value="1"/>'))
    cfg = bundle / f"{SID}.sumocfg"
    inputs = read_config(cfg)
    assert any("tlLogic 'n18' param file=" in d for d in inputs.dropped)
    with SumoSession(cfg) as sim:
        for _ in range(30):
            sim.step()
    assert list(outside.iterdir()) == []
    net = bundle / f"{SID}.net.xml"
    net.write_text(net.read_text().replace(
        '<tlLogic id="n18" type="static" programID="0" offset="0">',
        f'<tlLogic id="n18" type="actuated" programID="0" offset="0"><param key="file" '
        f'value="{outside}/net_det.xml"/>'))
    with pytest.raises(SumoConfigError, match=r"net.xml: tlLogic 'n18' param file=.*SUMO would "
                                              r"write detector output there"):
        read_config(cfg)


def test_route_includes_doctype_and_loops(tmp_path):
    """Route files are followed into their includes (a device param there is refused); a
    DOCTYPE (entities SUMO would expand) and an include loop are refused in one line."""
    inner = tmp_path / "types.xml"
    inner.write_text('<routes><vType id="t"><param key="has.ssm.device" value="true"/></vType>'
                     "</routes>")
    outer = tmp_path / "r.rou.xml"
    outer.write_text('<routes><include href="types.xml"/></routes>')
    with pytest.raises(SumoConfigError, match=r"types.xml: vType 't' param 'has.ssm.device'"):
        check_demand([outer])
    doc = tmp_path / "d.rou.xml"
    doc.write_text('<?xml version="1.0"?><!DOCTYPE routes [<!ENTITY x SYSTEM "file:///etc/x">]>'
                   "<routes>&x;</routes>")
    with pytest.raises(SumoConfigError, match=r"d.rou.xml: declares a DOCTYPE / ENTITY"):
        check_demand([doc])
    a, b = tmp_path / "a.rou.xml", tmp_path / "b.rou.xml"
    a.write_text('<routes><include href="b.rou.xml"/></routes>')
    b.write_text('<routes><include href="a.rou.xml"/></routes>')
    with pytest.raises(SumoConfigError, match=r"includes itself \(an include loop\)"):
        check_demand([a])
    net = ROOT / "networks" / SID / f"{SID}.net.xml"
    add = tmp_path / "e.add.xml"
    add.write_text('<!DOCTYPE additional [<!ENTITY e "x">]><additional/>')
    cfg = tmp_path / "c.sumocfg"
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<additional-files value="e.add.xml"/></configuration>')
    with pytest.raises(SumoConfigError, match=r"e.add.xml: declares a DOCTYPE / ENTITY"):
        read_config(cfg)


def test_a_bundles_route_file_is_checked_too(tmp_path):
    from converters.sumo.bundle import BundleError, BundleLayout

    bundle = tmp_path / SID
    shutil.copytree(ROOT / "networks" / SID, bundle)
    routes = bundle / f"{SID}.rou.xml"
    text = routes.read_text()
    i = text.index(">", text.index("<routes")) + 1
    routes.write_text(text[:i] + '<vType id="x"><param key="device.ssm.file" value="/tmp/o.xml"/>'
                      "</vType>" + text[i:])
    with pytest.raises(BundleError, match=r"rou.xml: vType 'x' param 'device.ssm.file'"):
        BundleLayout.of(bundle, SID).sumo_inputs()


def test_a_gzip_bomb_route_file_is_refused_at_the_cap(tmp_path, monkeypatch):
    import gzip

    from magail_sumo.sim import sumo_config

    monkeypatch.setattr(sumo_config, "STREAM_LIMIT", 1 << 20)
    bomb = tmp_path / "bomb.rou.xml.gz"
    bomb.write_bytes(gzip.compress(b"<routes>" + b" " * (4 << 20) + b"</routes>"))
    with pytest.raises(SumoConfigError, match=r"bomb.rou.xml.gz: unpacks to more than"):
        sumo_config._scan(bomb, lambda *a: None)


def test_an_include_bomb_is_refused_quickly(tmp_path):
    """Files including the next level 8 times each, 8 levels deep (a kilobyte in all, 8^8
    reads expanded): refused at the include budget within a second, in a route file and in an
    additional file alike."""
    from magail_sumo.sim.sumo_config import MAX_INCLUDED_FILES

    for i in range(8):
        (tmp_path / f"R{i}.rou.xml").write_text(
            "<routes>" + f'<include href="R{i + 1}.rou.xml"/>' * 8 + "</routes>")
        (tmp_path / f"L{i}.add.xml").write_text(
            "<additional>" + f'<include href="L{i + 1}.add.xml"/>' * 8 + "</additional>")
    (tmp_path / "R8.rou.xml").write_text('<routes><vType id="t"/></routes>')
    (tmp_path / "L8.add.xml").write_text('<additional><edgeData id="e" file="x.xml"/>'
                                          "</additional>")
    net = ROOT / "networks" / SID / f"{SID}.net.xml"
    start = time.perf_counter()
    with pytest.raises(SumoConfigError, match=rf"R0.rou.xml: includes more than "
                                              rf"{MAX_INCLUDED_FILES} files"):
        check_demand([tmp_path / "R0.rou.xml"])
    cfg = tmp_path / "a.sumocfg"
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<additional-files value="L0.add.xml"/></configuration>')
    with pytest.raises(SumoConfigError, match=r"L0.add.xml: includes more than"):
        read_config(cfg)
    assert time.perf_counter() - start < 5.0
    # a file included a few times over is fine
    (tmp_path / "ok.rou.xml").write_text("<routes>" + '<include href="R8.rou.xml"/>' * 20
                                         + "</routes>")
    check_demand([tmp_path / "ok.rou.xml"])


def test_files_sumo_reads_are_checked_with_their_includes(tmp_path):
    """A weight file and a variable speed sign's file are read by SUMO, includes and all: an
    include of a FIFO there is refused in one line naming it (SUMO would block on it); a
    corrupt gzipped route file is one line naming that file."""
    import gzip

    net = ROOT / "networks" / SID / f"{SID}.net.xml"
    os.mkfifo(tmp_path / "f")
    (tmp_path / "w.xml").write_text('<meandata><include href="f"/></meandata>')
    cfg = tmp_path / "w.sumocfg"
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<weight-files value="w.xml"/></configuration>')
    with pytest.raises(SumoConfigError, match=r"w.xml: include f: is a FIFO"):
        read_config(cfg)
    lane = next(iter(_lanes(net)))
    (tmp_path / "v.xml").write_text('<vss><include href="f"/></vss>')
    (tmp_path / "a.add.xml").write_text(
        f'<additional><variableSpeedSign id="v" lanes="{lane}" file="v.xml"/></additional>')
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<additional-files value="a.add.xml"/></configuration>')
    with pytest.raises(SumoConfigError, match=r"v.xml: include f: is a FIFO"):
        read_config(cfg)
    bad = tmp_path / "r.rou.xml.gz"
    bad.write_bytes(gzip.compress(b"<routes>" + b"<vType id='t'/>" * 999 + b"</routes>")[:-40]
                    + b"garbage")
    cfg.write_text(f'<configuration><net-file value="{net}"/>'
                   '<route-files value="r.rou.xml.gz"/></configuration>')
    with pytest.raises(SumoConfigError, match=r"r.rou.xml.gz: cannot read"):
        read_config(cfg)


def test_vehicle_type_classes_from_route_files(tmp_path):
    """Types of route files (includes followed) with their classes; a type naming none is a
    passenger car, as in SUMO; SUMO's built-in types are known."""
    from magail_sumo.sim.sumo_config import vtype_classes

    (tmp_path / "t.xml").write_text('<routes><vType id="b" vClass="bus"/></routes>')
    r = tmp_path / "r.rou.xml"
    r.write_text('<routes><include href="t.xml"/><vType id="car"/></routes>')
    got = vtype_classes([r])
    assert got["b"] == "bus" and got["car"] == "passenger"
    assert got["DEFAULT_VEHTYPE"] == "passenger" and got["DEFAULT_BIKETYPE"] == "bicycle"
