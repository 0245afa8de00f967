"""The restricted unpickler (``converters.scenarionet.safe_pickle``) and the ScenarioNet reader
on hostile pickles: memory corruption, allocation bombs, wrong-typed fields, one object
shared by thousands of tracks or map features.

Every crafted pickle is tiny and built here opcode by opcode; each must give one
:class:`UnsafePickleError` / one-line :class:`SceneFormatError`, never a crash, a traceback or
gigabytes of memory. Anything that could crash the interpreter on a regression runs in a
subprocess so that it cannot take pytest down.
"""

from __future__ import annotations

import collections
import copy
import json
import pickle
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR, peak_memory
from converters import iter_scene_records, load_scene
from converters.scenarionet import UnsafePickleError, load_scenarionet, safe_loads
from converters.scenarionet.safe_pickle import MIN_BUDGET, allocation_budget
from converters.scenarionet.writer import scene_to_scenarionet
from magail_sumo.errors import SceneFormatError


# ------------------------------------------------------------------ opcode builder

class _Op(bytes):
    """Raw pickle opcodes leaving one object on the stack."""


def _enc(x) -> bytes:
    if isinstance(x, _Op):
        return bytes(x)
    if isinstance(x, bool):
        return b"\x88" if x else b"\x89"
    if x is None:
        return b"N"
    if isinstance(x, int):
        if -2**31 <= x < 2**31:
            return b"J" + struct.pack("<i", x)
        n = (x.bit_length() + 8) // 8
        return b"\x8b" + struct.pack("<I", n) + x.to_bytes(n, "little", signed=True)
    if isinstance(x, float):
        return b"G" + struct.pack(">d", x)
    if isinstance(x, str):
        b = x.encode()
        return b"X" + struct.pack("<I", len(b)) + b
    if isinstance(x, bytes):
        return b"B" + struct.pack("<I", len(x)) + x
    if isinstance(x, tuple):
        return b"(" + b"".join(_enc(v) for v in x) + b"t"
    if isinstance(x, list):
        return b"](" + b"".join(_enc(v) for v in x) + b"e"
    if isinstance(x, dict):
        return b"}(" + b"".join(_enc(k) + _enc(v) for k, v in x.items()) + b"u"
    raise TypeError(x)


def _global(module: str, name: str) -> _Op:
    return _Op(b"c" + module.encode() + b"\n" + name.encode() + b"\n")


def _call(func: _Op, *args) -> _Op:
    return _Op(bytes(func) + _enc(tuple(args)) + b"R")


def _build(obj, state) -> _Op:
    return _Op(_enc(obj) + _enc(state) + b"b")


def _dump(x) -> bytes:
    return b"\x80\x03" + _enc(x) + b"."


ND = _global("numpy", "ndarray")
DT = _global("numpy", "dtype")
RECON = _global("numpy._core.multiarray", "_reconstruct")


def _dtype(code: str) -> _Op:
    return _call(DT, code)


def _array_state(shape, dtype: _Op, data) -> _Op:
    return _build(_call(RECON, ND, (0,), b"b"), (1, shape, dtype, False, data))


#: The 111-byte class of pickle that segfaulted the process: an object array whose element
#: pointers are the file's bytes.
SEGFAULT = _dump(_call(ND, (4,), _dtype("O8"), b"A" * 32))

GADGETS = {
    "object ndarray from file bytes": (SEGFAULT, "refused dtype '|O'"),
    "ObjectDType class": (_dump(_call(ND, (4,), _call(_global("numpy.dtypes", "ObjectDType")),
                                      b"A" * 32)), "refused to load numpy.dtypes.ObjectDType"),
    "direct ndarray, stride 0": (_dump(_call(ND, (10**6, 10**4), _dtype("f8"), b"A" * 8, 0, (0, 0))),
                                 "refused direct numpy.ndarray"),
    "object array via setstate": (_dump(_array_state((2,), _dtype("O8"), [1, 2])),
                                  "refused dtype '|O'"),
    "structured dtype with an object": (_dump(_array_state((1,), _dtype("i4,O"), [1])),
                                        "refused dtype"),
    "field outside its item": (_dump(_array_state((1,), _build(_dtype("V16"), (
        3, "|", None, ("a",), {"a": (_dtype("f8"), 100)}, 16, 1, 0)), b"A" * 16)),
        "requires 108 bytes, cannot override to smaller itemsize of 16"),
    "object _frombuffer": (_dump(_call(_global("numpy._core.numeric", "_frombuffer"), b"A" * 16,
                                       _dtype("O8"), (2,), "C")), "refused dtype '|O'"),
    "object scalar": (_dump(_call(_global("numpy._core.multiarray", "scalar"), _dtype("O8"),
                                  b"A" * 8)), "refused dtype '|O'"),
    "bytearray(4e9)": (_dump(_call(_global("builtins", "bytearray"), 4_000_000_000)),
                       "allocation budget"),
    "bytes(1e10)": (_dump(_call(_global("builtins", "bytes"), 10**10)), "allocation budget"),
    "list(range(1e9))": (_dump(_call(_global("builtins", "list"),
                                     _call(_global("builtins", "range"), 10**9))),
                         "allocation budget"),
    "dtype state numpy trusts (6-tuple)": (_dump(_array_state((1,), _build(_dtype("f8"), (
        3, "<", None, -1, -1, 0)), b"A" * 8)), "numpy.dtype: unexpected state"),
    "BUILD on a numpy scalar": (_dump(_build(_call(_global("numpy._core.multiarray", "scalar"),
                                                   _dtype("f8"), b"A" * 8), (1, 2, 3))),
                                "REFUSED"),  # a Python float now: BUILD fails cleanly
    "memo index 2**26 (1 GB memo table)": (b"\x80\x02N" + b"r" + struct.pack("<I", 2**26) + b".",
                                           "memo index 67108864 beyond the 9-byte pickle"),
    "protocol-0 PUT 2**26": (b"Np67108864\n.", "memo index 67108864 beyond the 12-byte pickle"),
    "bytearray8 claiming 2**62 bytes": (b"\x80\x05\x96" + (2**62).to_bytes(8, "little") + b"xx.",
                                        "truncated pickle: an opcode at byte 2 claims"),
    "zlib codec": (_dump(_call(_global("_codecs", "encode"), "abc", "zlib_codec")),
                   "refused codec 'zlib_codec'"),
    "unknown codec": (_dump(_call(_global("_codecs", "encode"), "abc", "no-such-codec")),
                      "refused codec 'no-such-codec'"),
}


@pytest.mark.parametrize("name", list(GADGETS))
def test_gadgets_are_refused_in_a_subprocess(tmp_path, name):
    data, message = GADGETS[name]
    path = tmp_path / "bad.pkl"
    path.write_bytes(data)
    code = ("import sys\nfrom converters.scenarionet.safe_pickle import safe_loads, LOAD_ERRORS\n"
            "try:\n    safe_loads(open(sys.argv[1], 'rb').read())\n"
            "except LOAD_ERRORS as exc:\n    print('REFUSED', exc)\n"
            "else:\n    print('REFUSED nothing to refuse (loaded)')\n")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT)
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert out.stdout.startswith("REFUSED") and message in out.stdout, out.stdout
    assert len(out.stdout.strip().splitlines()) == 1


def test_segfault_pickle_is_one_line_error_and_batch_goes_on(tmp_path):
    """inspect --skip-bad a.pkl bad.pkl c.pkl: bad.pkl is refused, a and c are read."""
    scene = load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    good = pickle.dumps(scene_to_scenarionet(scene), protocol=4)
    a, bad, c = tmp_path / "a.pkl", tmp_path / "bad.pkl", tmp_path / "c.pkl"
    a.write_bytes(good)
    c.write_bytes(good)
    bad.write_bytes(SEGFAULT)
    assert len(SEGFAULT) < 120
    cmd = [sys.executable, "-m", "magail_sumo.cli.main", "inspect", "--json"]
    out = subprocess.run([*cmd, str(bad)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 1, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "unsafe pickle" in lines[0], lines
    out = subprocess.run([*cmd, "--skip-bad", str(a), str(bad), str(c)], capture_output=True,
                         text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    ids = [json.loads(line)["scenario_id"] for line in out.stdout.splitlines()]
    assert ids == ["850c48d8bbfa008f", "850c48d8bbfa008f"]
    assert "read 2 scene(s) from 3 file(s); skipped 1" in out.stderr


@pytest.mark.sumo
def test_convert_skip_bad_goes_on_past_the_segfault_pickle(tmp_path):
    scene = load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    a, bad = tmp_path / "a.pkl", tmp_path / "bad.pkl"
    a.write_bytes(pickle.dumps(scene_to_scenarionet(scene), protocol=4))
    bad.write_bytes(SEGFAULT)
    out = subprocess.run([sys.executable, "-m", "magail_sumo.cli.main", "convert", "--out",
                          str(tmp_path / "out"), "--skip-bad", "--no-baseline", str(bad), str(a)],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = (tmp_path / "out" / "summary.csv").read_text().splitlines()
    assert rows[1].startswith(f"{bad},0,,unreadable,") and "unsafe pickle" in rows[1]
    assert rows[2].startswith(f"{a},0,850c48d8bbfa008f,ok,")


def test_claimed_length_beyond_the_file_is_truncated_not_allocated():
    data = b"\x80\x04\x8e" + (2**40).to_bytes(8, "little") + b"xx."
    with pytest.raises((pickle.UnpicklingError, MemoryError, EOFError)):
        safe_loads(data)


def test_budget_scales_with_file_size():
    assert allocation_budget(10) == MIN_BUDGET
    assert allocation_budget(10 << 20) == 640 << 20
    # a budget smaller than an honest array is refused; the default admits it
    arr = np.zeros(1000)
    with pytest.raises(UnsafePickleError, match="allocation budget"):
        safe_loads(pickle.dumps(arr, protocol=2), budget=4000)
    np.testing.assert_array_equal(safe_loads(pickle.dumps(arr, protocol=2)), arr)


@pytest.mark.parametrize("protocol", range(0, 6))
def test_plain_data_still_loads_in_every_protocol(protocol):
    value = {"f": np.arange(5.0, dtype=np.float32), "b": np.ones(3, bool), "i": np.int64(7),
             "s": np.array([(1, 2.0)], dtype=[("a", "<i4"), ("b", "<f8")]), "raw": b"\x00\xff",
             "d": collections.defaultdict(int, {"VEHICLE": 3}), "t": ("x", 1.5, None),
             "u": np.array(["ab", "c"])}
    back = safe_loads(pickle.dumps(value, protocol=protocol))
    for key in ("f", "b", "s", "u"):
        assert back[key].dtype == value[key].dtype
        np.testing.assert_array_equal(back[key], value[key])
    assert back["i"] == 7 and back["raw"] == b"\x00\xff" and back["t"] == ("x", 1.5, None)
    assert back["d"]["VEHICLE"] == 3 and back["d"]["missing"] == 0


# ------------------------------------------------------------------ wrong-typed fields

@pytest.fixture(scope="module")
def base_dict():
    return scene_to_scenarionet(load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord"))


def _lane(sd):
    return next(f for f in sd["map_features"].values() if f["type"].startswith("LANE"))


def _track(sd):
    return next(iter(sd["tracks"].values()))


def _set(get, key, value):
    return lambda sd: get(sd).__setitem__(key, value)


_META = lambda sd: sd["metadata"]  # noqa: E731
_TOP = lambda sd: sd  # noqa: E731
DEEP = "PLACEHOLDER_DEEP"

FIELDS = {
    "length 10**400": (_set(_TOP, "length", 10**400), "length: integer 1000", "out of range"),
    "speed 10**400": (_set(_lane, "speed_limit_mph", 10**400), ".speed_limit_mph: number",
                      "out of range"),
    "speed str": (_set(_lane, "speed_limit_mph", "fast"), ".speed_limit_mph",
                  "expected a number, got 'fast'"),
    "speed list": (_set(_lane, "speed_limit_mph", [1, 2]), ".speed_limit_mph",
                   "expected a number, got a list"),
    "speed array": (_set(_lane, "speed_limit_mph", np.zeros(3)), ".speed_limit_mph",
                    "expected a number, got an array of shape (3,)"),
    "neighbor list": (lambda sd: next(f for f in sd["map_features"].values()
                                      if f.get("left_neighbor"))["left_neighbor"].__setitem__(0, [1]),
                      ".left_neighbor[0]", "expected a dict, got list"),
    "tracks_to_predict array": (_set(_META, "tracks_to_predict", np.zeros(2)),
                                "metadata.tracks_to_predict", "expected a dict"),
    "interpolating array": (_set(_lane, "interpolating", np.ones(3)), ".interpolating",
                            "expected a bool"),
    "entry_lanes int": (_set(_lane, "entry_lanes", 5), ".entry_lanes", "expected a list, got 5"),
    "objects_of_interest int": (_set(_META, "objects_of_interest", 5),
                                "metadata.objects_of_interest", "expected a list, got 5"),
    "objects_of_interest str": (_set(_META, "objects_of_interest", ["a"]),
                                "metadata.objects_of_interest", "expected an integer, got 'a'"),
    "objects_of_interest 2-D": (_set(_META, "objects_of_interest", np.zeros((2, 2))),
                                "metadata.objects_of_interest", "array of shape (2, 2)"),
    "objects_of_interest 10**400": (_set(_META, "objects_of_interest", [10**400]),
                                    "metadata.objects_of_interest", "out of range"),
    "dynamic_map_states list": (_set(_TOP, "dynamic_map_states", [1]), "dynamic_map_states",
                                "expected a dict"),
    "dynamic_map_states value": (_set(_TOP, "dynamic_map_states", {"5": 7}),
                                 "dynamic_map_states['5']", "expected a dict, got int"),
    "object_state int": (_set(_TOP, "dynamic_map_states", {"5": {"state": {"object_state": 7}}}),
                         "dynamic_map_states['5'].state.object_state", "expected a list"),
    "object_state entry list": (
        _set(_TOP, "dynamic_map_states", {"5": {"state": {"object_state": [[1]] * 91}}}),
        "dynamic_map_states['5'].state[0]", "expected a type name, got a list"),
    "stop_point str": (_set(_TOP, "dynamic_map_states", {"5": {
        "state": {"object_state": [None] * 91}, "stop_point": "abc"}}),
        "dynamic_map_states['5'].stop_point", "expected a numeric array"),
    "track key 10**30": (lambda sd: sd["tracks"].__setitem__(str(10**30), sd["tracks"].pop(
        next(iter(sd["tracks"])))), "key", "out of range (64-bit)"),
    "heading 1e308": (lambda sd: _track(sd)["state"].__setitem__("heading", np.full(91, 1e308)),
                      ".state.heading", "value 1e+308 out of range"),
    "position 1e308": (lambda sd: _track(sd)["state"]["position"].__setitem__((3, 0), 1e308),
                       "step 3: field x is 1e+308", "out of range"),
    "scenario_id list": (_set(_META, "scenario_id", [1, 2]), "metadata.scenario_id",
                         "expected a string, got a list"),
    "feature type list": (_set(_lane, "type", [1]), ".type", "expected a string, got a list"),
    "deep ts": (_set(_META, "ts", DEEP), "metadata.ts", "expected a numeric array"),
    "deep scenario_id": (_set(_META, "scenario_id", DEEP), "metadata.scenario_id",
                         "expected a string, got a list"),
    "deep length": (_set(_TOP, "length", DEEP), "length", "expected an integer, got a list"),
    "deep position": (lambda sd: _track(sd)["state"].__setitem__("position", DEEP),
                      ".state.position", "expected a numeric array"),
}


def _pickle_with_deep_list(sd) -> bytes:
    """Protocol 2 pickle of ``sd`` with the :data:`DEEP` string replaced by a list nested
    100,000 deep (``pickle.dumps`` itself could not write it)."""
    data = pickle.dumps(sd, protocol=2)
    key = b"X" + struct.pack("<I", len(DEEP)) + DEEP.encode()
    if key not in data:
        return data
    return data.replace(key, b"]" * 100_000 + b"a" * 99_999)


@pytest.mark.parametrize("name", list(FIELDS))
def test_wrong_field_is_a_one_line_error_naming_file_and_field(tmp_path, base_dict, name):
    mutate, where, problem = FIELDS[name]
    sd = copy.deepcopy(base_dict)
    with np.errstate(over="ignore"):
        mutate(sd)
    path = tmp_path / "x.pkl"
    path.write_bytes(_pickle_with_deep_list(sd))
    with pytest.raises(SceneFormatError) as err:
        load_scenarionet(path)
    text = str(err.value)
    assert text.startswith(f"{path}: record 0: ") and "\n" not in text, text
    assert where in text and problem in text, text
    assert len(text) < 400


def test_real_scenarionet_files_read_as_before():
    """The shared ScenarioNet files that read before still read (when present)."""
    folder = ROOT.parent / "shared" / "data" / "scenarionet" / "womd"
    files = sorted(Path(folder).glob("*.pkl"))
    if not files:
        pytest.skip("no shared ScenarioNet data")
    ok = [r for f in files for r in iter_scene_records(f) if r.ok]
    assert len(ok) >= 5


@pytest.mark.parametrize("name, folder", [("../outside.pkl", ""), ("a/b.pkl", ""),
                                          ("sd_x.pkl", "../.."), ("sd_x.pkl", "/etc")])
def test_dataset_summary_names_stay_inside_the_folder(tmp_path, name, folder):
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "dataset_summary.pkl").write_bytes(pickle.dumps({name: {}}))
    (ds / "dataset_mapping.pkl").write_bytes(pickle.dumps({name: folder}))
    [rec] = list(iter_scene_records(ds))
    assert not rec.ok and "bad scenario file name" in str(rec.error), rec.error


# ------------------------------------------------------------------- objects shared across a pickle
MiB = 1 << 20


def _state(steps: int) -> dict:
    ones = np.ones(steps, bool)
    return {"position": np.zeros((steps, 2), bool), "heading": ones, "valid": ones,
            "length": ones, "width": ones, "height": ones}


def _load_peak(path):
    from converters.scenarionet import load_scenarionet
    from magail_sumo.errors import SceneFormatError

    def run():
        with pytest.raises(SceneFormatError) as err:
            load_scenarionet(path)
        return str(err.value)
    return peak_memory(run)


def test_tracks_sharing_one_state_cannot_blow_up(tmp_path):
    """5000 tracks referencing one 20000-step state: a 300 kB pickle describing a 6 GB scene."""
    import pickle

    state = _state(20_000)
    sd = {"id": "x", "length": 20_000, "map_features": {}, "dynamic_map_states": {},
          "metadata": {"ts": np.arange(20_000, dtype=np.int32), "scenario_id": "x"},
          "tracks": {str(i): {"type": "VEHICLE", "state": state} for i in range(5000)}}
    path = tmp_path / "shared.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    assert path.stat().st_size < 400_000
    text, peak = _load_peak(path)
    assert text.startswith(f"{path}: record 0: tracks: the scene would take more than 67108864 "
                           "bytes of memory"), text
    assert peak < 64 * MiB


def test_map_features_sharing_one_polyline_cannot_blow_up(tmp_path):
    import pickle

    poly = np.zeros((100_000, 2), bool)
    sd = {"id": "x", "length": 2, "dynamic_map_states": {},
          "metadata": {"ts": np.arange(2.0), "scenario_id": "x"},
          "tracks": {"1": {"type": "VEHICLE", "state": _state(2)}},
          "map_features": {str(i): {"type": "ROAD_EDGE_BOUNDARY", "polyline": poly}
                           for i in range(10, 20_000)}}
    path = tmp_path / "shared_map.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    text, peak = _load_peak(path)
    assert "].polyline: the scene would take more than 67108864 bytes" in text, text
    assert peak < 128 * MiB


def test_a_pickle_larger_than_any_scene_is_refused_by_its_size(tmp_path):
    """A 3 GiB (sparse) file is refused from its size, before a byte is read."""
    import time

    from converters.scenarionet import load_scenarionet
    from magail_sumo.errors import SceneFormatError

    big = tmp_path / "big.pkl"
    with open(big, "wb") as fh:
        fh.truncate(3 << 30)
    t0 = time.monotonic()
    with pytest.raises(SceneFormatError, match=r"big.pkl: record 0: 3.0 GiB, more than the 1 GiB"):
        load_scenarionet(big)
    assert time.monotonic() - t0 < 2
