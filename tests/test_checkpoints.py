"""Training checkpoints and run directories: a checkpoint cannot run code, bad checkpoints
give one-line errors naming the file (in training and in evaluation), ``train --overwrite``
removes only a run (and nothing when the folder's marker is not valid), nothing is written
through a symbolic link out of a run directory, and a full disk is one line naming the file."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from conftest import WOMD_DIR, tree_digest
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict, to_dict
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.expert import record_expert
from magail_sumo.outputs import MARKER, OutputError
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.trainer import (CHECKPOINT_FORMAT, CheckpointError, _rng_state,
                                          load_checkpoint, load_policy, make_policy, train,
                                          upgrade_checkpoint)

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")


class _Boom:
    """Unpickling this runs ``touch MARKER``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _craft(path: Path, marker: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": CHECKPOINT_FORMAT, "update": 0, "config": {}, "policy": _Boom(marker)},
               path)
    return path


def _one_line_error(err: str, name: str) -> str:
    lines = [s for s in err.splitlines() if s.startswith("error:")]
    assert len(lines) == 1 and name in lines[0], err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("hard_ckpt")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 2, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 1, "env": {"max_steps": 20},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [8], "critic_hidden": [8]},
        "ppo": {"n_steps": 8, "batch_size": 16, "n_epochs": 1},
        "discriminator": {"kind": "mlp", "mlp_hidden": [8], "epochs": 1, "batch_size": 4},
        "bc": {"epochs": 1, "batch_size": 64}})
    cfg_path = root / "cfg.yaml"
    cfg_path.write_text(yaml.safe_dump(to_dict(cfg)))
    return root, cfg, cfg_path


@pytest.fixture(scope="module")
def gail_run(setup):
    root, cfg, _ = setup
    return train(cfg, run_dir=root / "gail", log=lambda s: None)


def test_crafted_checkpoint_refused_by_evaluate(tmp_path, capsys):
    marker = tmp_path / "MARKER"
    bad = _craft(tmp_path / "crafted.pt", marker)
    rc = main(["evaluate", "--policy", str(bad), "--scenes", SCENE, "--rollouts", "1",
               "--baselines", "none", "--out", str(tmp_path / "eval")])
    assert rc == 1 and not marker.exists()
    line = _one_line_error(capsys.readouterr().err, "crafted.pt")
    assert "posix.system" in line or "refused" in line


@pytest.mark.sumo
def test_crafted_latest_refused_by_resume(setup, tmp_path, capsys):
    _, _, cfg_path = setup
    marker = tmp_path / "MARKER"
    run = tmp_path / "run"
    _craft(run / "checkpoints" / "latest.pt", marker)
    rc = main(["train", "--config", str(cfg_path), "--resume", str(run)])
    assert rc == 1 and not marker.exists()
    _one_line_error(capsys.readouterr().err, "latest.pt")
    with pytest.raises(CheckpointError, match="refused"):
        load_policy(run / "checkpoints" / "latest.pt")
    assert not marker.exists()


@pytest.mark.sumo
def test_checkpoint_holds_only_tensors_and_plain_data(gail_run):
    state = torch.load(gail_run / "checkpoints" / "latest.pt", weights_only=True)
    assert state["format"] == "magail_sumo.checkpoint/2"

    def walk(v):
        if isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, (list, tuple)):
            for x in v:
                walk(x)
        else:
            assert v is None or isinstance(v, (torch.Tensor, str, int, float, bool)), type(v)

    walk(state)


def _format1_bc(setup, path: Path) -> Path:
    """A format-1 (behavioural cloning) checkpoint as earlier versions wrote it."""
    _, cfg, _ = setup
    cfg = replace(cfg, algorithm="bc")
    torch.save({"format": "magail_sumo.checkpoint/1", "update": 0, "config": to_dict(cfg),
                "policy": make_policy(cfg).state_dict(), "rng": _rng_state()}, path)
    return path


@pytest.mark.sumo
def test_format1_refused_and_trusted_upgrade(setup, tmp_path):
    old = _format1_bc(setup, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match=r"old\.pt: .*older magail_sumo version.*unsafe"
                       ) as exc:
        load_checkpoint(old)
    assert "\n" not in str(exc.value)
    with pytest.raises(CheckpointError, match="trust"):
        upgrade_checkpoint(old)
    new = upgrade_checkpoint(old, tmp_path / "new.pt", trust=True)
    assert load_checkpoint(new)["format"] == CHECKPOINT_FORMAT
    policy, cfg = load_policy(new)
    assert cfg.algorithm == "bc"
    # the CLI: refused without --trust, in place with it
    assert main(["train", "--upgrade-checkpoint", str(old)]) == 1
    assert main(["train", "--upgrade-checkpoint", str(old), "--trust"]) == 0
    assert load_checkpoint(old)["format"] == CHECKPOINT_FORMAT
    assert main(["train"]) == 1  # --config still needed to train


def _edited(run: Path, tmp_path: Path, edit) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run, dst)
    path = dst / "checkpoints" / "latest.pt"
    state = torch.load(path, weights_only=True)
    edit(state)
    torch.save(state, path)
    return dst


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.__setitem__("rng", {"torch": "x", "numpy": 1, "python": None}), "rng"),
    (lambda s: s.pop("last_obs"), "lacks last_obs"),
])
@pytest.mark.sumo
def test_bad_resume_state_is_one_line(setup, gail_run, tmp_path, edit, message):
    _, cfg, _ = setup
    run = _edited(gail_run, tmp_path, edit)
    with pytest.raises(CheckpointError, match=message) as exc:
        train(replace(cfg, updates=2), resume=run, log=lambda s: None)
    text = str(exc.value)
    assert "\n" not in text and "latest.pt" in text and len(text) < 400


@pytest.mark.sumo
def test_state_dict_mismatch_is_summarised(gail_run, tmp_path):
    def edit(state):
        pol = state["policy"]
        for k in [k for k in pol if "normalizer" not in k]:
            del pol[k]
        pol["bogus.weight"] = torch.zeros(2)

    run = _edited(gail_run, tmp_path, edit)
    with pytest.raises(CheckpointError, match=r"latest\.pt: .*missing keys .*\(\+\d+ more\); "
                                              r"unexpected keys bogus\.weight") as exc:
        load_policy(run / "checkpoints" / "latest.pt")
    assert "\n" not in str(exc.value)


@pytest.mark.sumo
def test_invalid_config_in_checkpoint_names_the_file(gail_run, tmp_path):
    state = torch.load(gail_run / "checkpoints" / "latest.pt", weights_only=True)
    state["config"]["ppo"]["n_steps"] = 0
    torch.save(state, tmp_path / "badcfg.pt")
    with pytest.raises(CheckpointError, match=r"badcfg\.pt: .*ppo\.n_steps: must be >= 1"):
        load_policy(tmp_path / "badcfg.pt")


@pytest.mark.sumo
def test_resume_state_round_trip_is_exact(setup, gail_run, tmp_path):
    """Resume of the saved run reaches the same state as a straight run (checked in detail by
    tests/test_training.py); here: the decoded numpy parts are bit-identical to the saved ones."""
    state = torch.load(gail_run / "checkpoints" / "latest.pt", weights_only=True)
    assert state["last_obs"].dtype == torch.float32
    assert state["last_episode_starts"].dtype == torch.bool
    assert state["rng"]["numpy"][1].shape == (624,)
    assert all(isinstance(a, torch.Tensor) for _, a in state["env_state"])


# --- train --overwrite ------------------------------------------------------------------------

def _bc_config(setup, tmp_path) -> Path:
    _, cfg, _ = setup
    p = tmp_path / "bc.yaml"
    p.write_text(yaml.safe_dump(to_dict(replace(cfg, algorithm="bc"))))
    return p


@pytest.mark.sumo
def test_overwrite_refuses_a_folder_train_did_not_write(setup, tmp_path, capsys):
    cfg = _bc_config(setup, tmp_path)
    d = tmp_path / "project"
    (d / "src").mkdir(parents=True)
    (d / "src" / "main.py").write_text("print(1)\n")
    (d / "data.csv").write_text("a,b\n1,2\n")
    (d / "config.yaml").write_text("mine: true\n")
    before = sorted(str(p.relative_to(d)) for p in d.rglob("*"))
    assert main(["train", "--config", str(cfg), "--run-dir", str(d), "--overwrite"]) == 1
    _one_line_error(capsys.readouterr().err, str(d))
    assert sorted(str(p.relative_to(d)) for p in d.rglob("*")) == before
    assert (d / "data.csv").read_text() == "a,b\n1,2\n"


@pytest.mark.sumo
def test_overwrite_replaces_a_run_and_keeps_user_files(setup, tmp_path):
    cfg = _bc_config(setup, tmp_path)
    d = tmp_path / "run"
    assert main(["train", "--config", str(cfg), "--run-dir", str(d)]) == 0
    first = load_checkpoint(d / "checkpoints" / "latest.pt")
    (d / "checkpoints" / "stale.pt").write_bytes(b"x")
    (d / "notes.txt").write_text("keep me")
    # without --overwrite a run is not replaced
    assert main(["train", "--config", str(cfg), "--run-dir", str(d)]) == 1
    assert main(["train", "--config", str(cfg), "--run-dir", str(d), "--seed", "9",
                 "--overwrite"]) == 0
    assert (d / "notes.txt").read_text() == "keep me"
    assert not (d / "checkpoints" / "stale.pt").exists()
    assert load_checkpoint(d / "checkpoints" / "latest.pt")["config"]["seed"] == 9
    assert first["config"]["seed"] == 2
    assert yaml.safe_load((d / "config.yaml").read_text())["seed"] == 9
    # and again: the folder stays a run directory
    assert main(["train", "--config", str(cfg), "--run-dir", str(d), "--overwrite"]) == 0
    assert (d / "notes.txt").read_text() == "keep me"
    assert not list(d.glob(".*.tmp")) and not list((d / "checkpoints").glob(".*.tmp"))


@pytest.mark.sumo
def test_new_run_refuses_a_foreign_folder(setup, tmp_path):
    _, cfg, _ = setup
    d = tmp_path / "foreign"
    d.mkdir()
    (d / "x.txt").write_text("x")
    with pytest.raises(Exception, match="not empty"):
        train(replace(cfg, algorithm="bc"), run_dir=d, log=lambda s: None)
    assert sorted(p.name for p in d.iterdir()) == ["x.txt"]
    np.testing.assert_equal((d / "x.txt").read_text(), "x")


@pytest.mark.sumo
def test_failed_set_up_leaves_no_run_dir(setup, tmp_path):
    _, cfg, _ = setup
    with pytest.raises(Exception):
        train(replace(cfg, algorithm="bc", expert_dir=str(tmp_path / "no_expert")),
              run_dir=tmp_path / "run", log=lambda s: None)
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------------------- evaluate
def test_unloadable_checkpoint_is_one_line(tmp_path, capsys):
    ckpt = tmp_path / "broken.pt"
    ckpt.write_bytes(b"not a checkpoint")
    rc = main(["evaluate", "--policy", str(ckpt), "--baselines", "none", "--scenes", str(SCENE),
               "--out", str(tmp_path / "e")])
    assert rc == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: magail-sumo evaluate: ")
    assert str(ckpt) in err[0] and "Traceback" not in err[0]


# --- writes stay in the run directory ------------------------------------------------------
def _outside(tmp_path: Path) -> Path:
    """tmp/outside/: a sibling of the run directory holding a file that must never change."""
    o = tmp_path / "outside"
    o.mkdir()
    (o / "precious.tsv").write_text("my data\n")
    return o


def _refused(err: str, path: Path) -> None:
    line = _one_line_error(err, str(path))
    assert f"{path}: would be written outside" in line, line


def _yaml(cfg, path: Path) -> Path:
    path.write_text(yaml.safe_dump(to_dict(cfg)))
    return path


@pytest.mark.parametrize("name", ["checkpoints", "skipped_scenes.tsv", "tb", "config.yaml",
                                  "environment.json"])
def test_run_dir_write_sites_refuse_links_out(tmp_path, name):
    """Each place a run writes (checkpoints, the skipped-scenes append, TensorBoard, the run
    record) refuses a symbolic link out of the run directory; nothing outside changes."""
    from types import SimpleNamespace

    from magail_sumo.config import record_run
    from magail_sumo.training.trainer import note_skipped, save_checkpoint

    def tb_logger(d: Path):
        from magail_sumo.training.loop import tb_logger

        return tb_logger(d)

    run, outside = tmp_path / "run", _outside(tmp_path)
    run.mkdir()
    link = run / name
    link.symlink_to(outside / "precious.tsv" if "." in name else outside)
    before = tree_digest(outside)
    write = {"checkpoints": lambda: save_checkpoint(run, {"update": 1}, 1),
             "skipped_scenes.tsv": lambda: note_skipped(
                 SimpleNamespace(new_skipped=[("a.pkl", "unreadable")]), run),
             "tb": lambda: tb_logger(run),
             "config.yaml": lambda: record_run(run, TrainConfig()),
             "environment.json": lambda: record_run(run, TrainConfig())}[name]
    with pytest.raises(OutputError, match=f"{link}: would be written outside") as e:
        write()
    assert "\n" not in str(e.value)
    assert tree_digest(outside) == before


@pytest.fixture(scope="module")
def pool_run(setup, tmp_path_factory):
    """A 1-update gail run on a pool folder (scene 850c and a file that is not a scene: the
    run lists it in skipped_scenes.tsv), and its config."""
    root, cfg, _ = setup
    pool = tmp_path_factory.mktemp("pool")
    shutil.copy(SCENE, pool / Path(SCENE).name)
    (pool / "broken.pkl").write_bytes(b"\x80\x04not a pickle at all")
    pcfg = replace(cfg, scenes=replace(cfg.scenes, files=[str(pool)]))
    run = train(pcfg, run_dir=root / "pool_run", log=lambda s: None)
    assert len((run / "skipped_scenes.tsv").read_text().splitlines()) == 2
    assert (run / "tb").is_dir() and (run / "checkpoints" / "latest.pt").is_file()
    return run, pcfg


@pytest.mark.sumo
@pytest.mark.parametrize("name", ["skipped_scenes.tsv", "tb", "checkpoints"])
def test_resume_refuses_links_out_of_the_run_dir(pool_run, tmp_path, capsys, name):
    """``train --resume RUN`` where RUN/skipped_scenes.tsv is a link to a file outside (it
    would gain the skipped scene's line), or RUN/tb or RUN/checkpoints a link to the run's own
    folder moved outside (new event files, new checkpoints): refused in one line naming the
    link, before the set-up; nothing outside changes."""
    run, pcfg = pool_run
    d = tmp_path / "run"
    shutil.copytree(run, d)
    outside = _outside(tmp_path)
    if name == "skipped_scenes.tsv":
        (d / name).unlink()
        (d / name).symlink_to(outside / "precious.tsv")
    else:
        shutil.move(d / name, outside / name)
        (d / name).symlink_to(outside / name)
    before = tree_digest(outside)
    cfg = _yaml(replace(pcfg, updates=2), tmp_path / "cfg.yaml")
    assert main(["train", "--config", str(cfg), "--resume", str(d)]) == 1
    _refused(capsys.readouterr().err, d / name)
    assert tree_digest(outside) == before


@pytest.mark.sumo
def test_new_run_refuses_a_dangling_link_out(pool_run, tmp_path, capsys):
    """A new run into a folder marked as train's holding only a dangling
    skipped_scenes.tsv link out of it: refused; the link's target is not created."""
    _, pcfg = pool_run
    d = tmp_path / "run"
    d.mkdir()
    (d / MARKER).write_text(json.dumps({"tools": {"train": []}}))
    outside = _outside(tmp_path)
    (d / "skipped_scenes.tsv").symlink_to(outside / "new.tsv")
    cfg = _yaml(pcfg, tmp_path / "cfg.yaml")
    assert main(["train", "--config", str(cfg), "--run-dir", str(d)]) == 1
    _refused(capsys.readouterr().err, d / "skipped_scenes.tsv")
    assert sorted(os.listdir(outside)) == ["precious.tsv"]
    assert sorted(os.listdir(d)) == [MARKER, "skipped_scenes.tsv"]


@pytest.mark.sumo
def test_bc_checkpoint_refuses_a_link_out(setup, tmp_path):
    """Behavioural cloning's own checkpoint write (train_bc, past the run-directory checks)."""
    from magail_sumo.training.bc import train_bc

    _, cfg, _ = setup
    run, outside = tmp_path / "run", _outside(tmp_path)
    run.mkdir()
    (run / MARKER).write_text(json.dumps({"tools": {"train": []}}))
    (run / "checkpoints").symlink_to(outside)
    before = tree_digest(outside)
    with pytest.raises(OutputError, match="checkpoints: would be written outside"):
        train_bc(replace(cfg, algorithm="bc"), run, None, lambda s: None,
                 lambda *a: None)
    assert tree_digest(outside) == before


# --- markers and full disks: one line naming the file ------------------------------------
@pytest.mark.sumo
def test_overwrite_with_an_invalid_marker_names_the_marker(setup, tmp_path, capsys):
    cfg = _bc_config(setup, tmp_path)
    d = tmp_path / "run"
    d.mkdir()
    (d / MARKER).write_text("[" * 100000)  # too deep for the JSON parser
    (d / "config.yaml").write_text("mine\n")
    before = tree_digest(d)
    assert main(["train", "--config", str(cfg), "--run-dir", str(d), "--overwrite"]) == 1
    line = _one_line_error(capsys.readouterr().err, str(d / MARKER))
    assert "not a valid magail_sumo marker (nested too deep)" in line
    assert "nothing removed" in line and str(cfg) not in line
    assert tree_digest(d) == before


def _big_bc_config(setup, tmp_path) -> Path:
    """Behavioural cloning of a policy whose checkpoint is a few MiB."""
    _, cfg, _ = setup
    big = replace(cfg, algorithm="bc", policy=replace(cfg.policy, actor_hidden=[512, 512],
                                                      critic_hidden=[512, 512]))
    return _yaml(big, tmp_path / "bc.yaml")


@pytest.mark.sumo
@pytest.mark.parametrize("how", ["tmpfs", "file-size limit"])
def test_full_disk_during_train_is_one_line_naming_the_file(setup, tmp_path, capsys, how):
    """A checkpoint write that fails for a real OS reason (a full 256 KiB tmpfs: ENOSPC; a
    256 KiB file-size limit, RLIMIT_FSIZE: EFBIG) ends train with one line naming the
    checkpoint and the reason; no partial file is left."""
    import errno
    import resource
    import signal

    from conftest import small_tmpfs

    cfg = _big_bc_config(setup, tmp_path)
    with contextlib.ExitStack() as stack:
        if how == "tmpfs":
            base = stack.enter_context(small_tmpfs(tmp_path / "small", "256k"))
            reason = os.strerror(errno.ENOSPC)
        else:
            base = tmp_path
            reason = os.strerror(errno.EFBIG)
            soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
            old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            stack.callback(signal.signal, signal.SIGXFSZ, old)
            resource.setrlimit(resource.RLIMIT_FSIZE, (256 << 10, hard))
            stack.callback(resource.setrlimit, resource.RLIMIT_FSIZE, (soft, hard))
        run = base / "run"
        rc = main(["train", "--config", str(cfg), "--run-dir", str(run)])
        err = capsys.readouterr().err
        assert rc == 1
        line = _one_line_error(err, str(run / "checkpoints" / "latest.pt"))
        assert line.endswith(f"{run / 'checkpoints' / 'latest.pt'}: cannot write ({reason})")
        assert len(err.strip().splitlines()) == 1
        assert os.listdir(run / "checkpoints") == []  # no temporary file left
        assert yaml.safe_load((run / "config.yaml").read_text())["algorithm"] == "bc"
