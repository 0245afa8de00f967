"""Configs that compose: ``extends``, ``magail-sumo train --set``, scenes taken from a split, and
the proof that every published config resolves to exactly the settings it was trained with.

``tests/data/configs_resolved/<old name>.json`` are the 34 flat training configs that
``configs/*.yaml`` held before they were split into ``configs/algorithms``, ``configs/scenes``
and ``configs/experiments`` (commit 3ad1f57): each loaded by that commit's loader and written
with every setting, defaults included (``json.dumps(to_dict(cfg), sort_keys=True)``). They are
frozen: :data:`MOVED` maps each old name to its file now, and
:func:`test_published_config_resolves_to_its_flat_file` compares the two setting for setting.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from magail_sumo.config import (MAX_EXTENDS_DEPTH, MAX_EXTENDS_FILES, MAX_MESSAGE, ConfigError,
                                compose_config, count_settings, from_dict, load_config,
                                parse_override, record_run, to_dict)
from magail_sumo.splits import load_split
from magail_sumo.training.config import ScenesConfig, TrainConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
RESOLVED = Path(__file__).resolve().parent / "data" / "configs_resolved"
SPLIT = CONFIGS / "splits" / "womd14.yaml"

#: old flat config (``configs/<name>.yaml``) -> its file now, under ``configs/``
MOVED = {
    "demo": "demo.yaml",
    "magail": "experiments/womd3/magail.yaml",
    "magail_small": "experiments/womd3/magail_small.yaml",
    "magail_tcritic": "experiments/womd3/magail_tcritic.yaml",
    "magail_scratch": "experiments/womd3/magail_scratch.yaml",
    "magail_tuned": "experiments/womd3/magail_tuned.yaml",
    "magail_bcreg": "experiments/womd3/magail_bcreg.yaml",
    "magail_windows": "experiments/womd3/magail_windows.yaml",
    "magail_decomposed": "experiments/womd3/magail_decomposed.yaml",
    "magail_decomposed_social": "experiments/womd3/magail_decomposed_social.yaml",
    "gail_mlp": "experiments/womd3/gail_mlp.yaml",
    "gail_mlp_small": "experiments/womd3/gail_mlp_small.yaml",
    "gail_mlp_scratch": "experiments/womd3/gail_mlp_scratch.yaml",
    "gail_mlp_tuned": "experiments/womd3/gail_mlp_tuned.yaml",
    "bc": "experiments/womd3/bc.yaml",
    "womd14_magail": "experiments/womd14/magail.yaml",
    "womd14_gail_mlp": "experiments/womd14/gail_mlp.yaml",
    "womd14_bc": "experiments/womd14/bc.yaml",
    "womd14_decomposed": "experiments/womd14/decomposed.yaml",
    "womd14_decomposed_bcreg": "experiments/womd14/decomposed_bcreg.yaml",
    "womd14_decomposed_destination": "experiments/womd14/decomposed_destination.yaml",
    "womd14_decomposed_wholelog": "experiments/womd14/decomposed_wholelog.yaml",
    "womd14_decomposed_social": "experiments/womd14/decomposed_social.yaml",
    "womd14_decomposed_social_bcreg": "experiments/womd14/decomposed_social_bcreg.yaml",
    "womd14_decomposed_social_leader": "experiments/womd14/decomposed_social_leader.yaml",
    "womd14_decomposed_social_route": "experiments/womd14/decomposed_social_route.yaml",
    "womd14_decomposed_social_leader_edge":
        "experiments/womd14/decomposed_social_leader_edge.yaml",
    "womd14_decomposed_social_leader_guard":
        "experiments/womd14/decomposed_social_leader_guard.yaml",
    "womd14_decomposed_social_leader_edge_guard":
        "experiments/womd14/decomposed_social_leader_edge_guard.yaml",
    "womd14_decomposed_social_leader_edge_guard_eol":
        "experiments/womd14/decomposed_social_leader_edge_guard_eol.yaml",
    "sac_task": "experiments/womd14/sac_task.yaml",
    "sac_gail": "experiments/womd14/sac_gail.yaml",
    "gameformer": "experiments/womd14/gameformer.yaml",
    "city_ingolstadt21": "experiments/city/ingolstadt21.yaml",
}

#: the files a user trains with: the experiments and the README demo
EXPERIMENTS = sorted([*(CONFIGS / "experiments").rglob("*.yaml"), CONFIGS / "demo.yaml"])


def flat(data: dict, path: str = "") -> dict:
    """Dotted key -> value of every setting of a nested mapping."""
    out = {}
    for key, value in data.items():
        where = f"{path}.{key}" if path else key
        out.update(flat(value, where) if isinstance(value, dict) else {where: value})
    return out


def resolved(path: Path, overrides=()) -> dict:
    """Every setting of the config file ``path`` as plain JSON data (tuples as lists)."""
    return flat(json.loads(json.dumps(to_dict(load_config(path, TrainConfig, overrides)))))


# --- the published configs --------------------------------------------------------------


def test_the_frozen_flat_configs_are_the_34_of_the_table():
    assert sorted(p.stem for p in RESOLVED.glob("*.json")) == sorted(MOVED)
    assert len(MOVED) == 34 and len(set(MOVED.values())) == 34
    # the old paths hold no copy: a config lives in one place
    assert [p.name for p in CONFIGS.glob("*.yaml")] == ["demo.yaml"]


#: settings added to TrainConfig after the flat files were frozen, with their defaults. The
#: node_ip default keeps the old behaviour; city.agent_classes does not where a city has other
#: classes: before it every vehicle could become an agent (ingolstadt21's buses did in the
#: published city runs), now only passenger cars (issue 32); the city task reward, the red-light
#: penalty and route-relative control's offset range (issue 32) default to none / unused;
#: the release of junctions agents and SUMO's drivers block (city.unblock_s, issue 32) is on
#: (10 s): runs before it had none; the speed-limit observation (issue 32) is off
ADDED_SINCE = {"workers.ray.node_ip": None, "city.agent_classes": ["passenger"],
               "city.progress_reward": 0.0, "discriminator.red_light_penalty": 0.0,
               "env.limits.max_offset": 1.5, "discriminator.decomposed_transformer.embed_dim": 64,
               "discriminator.decomposed_transformer.num_layers": 2,
               "discriminator.decomposed_transformer.num_heads": 4,
               "discriminator.decomposed_transformer.ff_dim": 128,
               "discriminator.decomposed_transformer.dropout": 0.0,
               "env.limits.max_steer_rate": 0.0, "env.observation.light_gap": False,
               "env.observation.give_way": False, "policy.action_prior": "none",
               "city.agent_tight_turns": False, "env.observation.path_leader": False,
               "city.unblock_s": 10.0, "env.observation.speed_limit": False,
               "workers.scenes_per_env": 1, "ppo.prior_coef": 0.0,
               "env.observation.give_way_conflicts": False, "env.observation.route_stop": False,
               "env.observation.speed_factor": False, "city.demand_scale": 1.0}
#: the demo's folders, moved into out/quickstart/ (issue 35: every README section has its own)
DEMO_MOVED = {"expert_dir": "out/quickstart/expert", "scenes.networks": "out/quickstart/networks",
              "out_dir": "out/quickstart/runs"}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_published_config_resolves_to_its_flat_file(old):
    want = flat(json.loads((RESOLVED / f"{old}.json").read_text()))
    got = resolved(CONFIGS / MOVED[old])
    if old == "demo":
        want |= DEMO_MOVED
    for key, value in ADDED_SINCE.items():
        assert got.pop(key) == value, f"{MOVED[old]}: {key} is not {value!r}"
    assert sorted(got) == sorted(want), f"{MOVED[old]}: settings differ from configs/{old}.yaml"
    for key, value in want.items():
        assert got[key] == value and type(got[key]) is type(value), \
            f"{MOVED[old]}: {key} is {got[key]!r}, configs/{old}.yaml trained with {value!r}"


def test_the_table_is_in_configs_readme():
    lines = (CONFIGS / "README.md").read_text().splitlines()
    for old, new in MOVED.items():
        assert any(f"configs/{old}.yaml" in line and f"configs/{new}" in line for line in lines), \
            f"configs/README.md does not map configs/{old}.yaml to configs/{new}"


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: str(p.relative_to(CONFIGS)))
def test_experiment_file_holds_only_its_change(path, tmp_path):
    """At most 15 settings, none restating what the file's bases (or the defaults) give."""
    own = yaml.safe_load(path.read_text())
    assert count_settings(own) <= 15, f"{path.name}: {count_settings(own)} settings"
    bases = own.get("extends", [])
    bases = [bases] if isinstance(bases, str) else bases
    just_bases = tmp_path / "bases.yaml"  # the same bases, by absolute path
    just_bases.write_text(yaml.safe_dump({"extends": [str(path.parent / b) for b in bases]}))
    inherited = resolved(just_bases)
    full = resolved(path)
    restated = [k for k in flat({k: v for k, v in own.items() if k != "extends"})
                if k in inherited and full[k] == inherited[k]]
    assert not restated, f"{path.name} restates {restated}"


def test_pretrained_cards_record_the_settings_of_their_experiment():
    """The checkpoint cards record the config each published checkpoint trained with; it is its
    experiment file's, but for the settings the card's description names (seed, worker count)
    and the settings added to TrainConfig since (absent from the card: their defaults)."""
    cards = {"magail_womd14": ("womd14/magail", set()),
             "decomposed_social_womd14": ("womd14/decomposed_social", set()),
             "leader_edge_guard_womd14": ("womd14/decomposed_social_leader_edge_guard",
                                          {"seed", "workers.count"}),
             "leader_edge_guard_eol_womd14": ("womd14/decomposed_social_leader_edge_guard_eol",
                                              {"workers.count"}),
             # its scene paths are under the split's data_root, which the environment may move
             "leader_edge_guard_eol_wild60": ("wild/long", {"scenes.files"})}
    for card, (name, named) in cards.items():
        text = json.loads((ROOT / "magail_sumo" / "pretrained" / f"{card}.json").read_text())
        assert f"configs/experiments/{name}.yaml" in text["description"]
        got = resolved(CONFIGS / "experiments" / f"{name}.yaml")
        for key, value in flat(text["config"]).items():
            if key not in named:
                assert got[key] == value, f"{card}: {key} {value!r}, {name}.yaml {got[key]!r}"
        stems = [Path(f).name for f in text["config"]["scenes"]["files"]]
        assert stems == [Path(f).name for f in got["scenes.files"]], card


# --- extends ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Inner:
    lr: float = 1e-3
    layers: tuple[int, ...] = (64, 64)


@dataclass(frozen=True)
class Outer:
    seed: int = 0
    name: str = "x"
    inner: Inner = field(default_factory=Inner)

    def __post_init__(self) -> None:
        from magail_sumo.config import check

        check(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def refused(path: Path, match: str, cls=Outer, overrides=()) -> str:
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path, cls, overrides)
    message = str(info.value)
    assert "\n" not in message and len(message) <= MAX_MESSAGE
    return message


def test_extends_deep_merges_maps_and_replaces_lists(tmp_path):
    write(tmp_path / "base.yaml", "seed: 1\nname: base\ninner:\n  lr: 2\n  layers: [8, 8, 8]\n")
    child = write(tmp_path / "child.yaml", "extends: base.yaml\ninner:\n  layers: [4]\n")
    assert load_config(child, Outer) == Outer(seed=1, name="base", inner=Inner(lr=2.0, layers=(4,)))


def test_extends_list_later_bases_win_and_the_file_last(tmp_path):
    write(tmp_path / "a.yaml", "seed: 1\nname: a\n")
    write(tmp_path / "b.yaml", "seed: 2\ninner: {lr: 3}\n")
    child = write(tmp_path / "c.yaml", "extends: [a.yaml, b.yaml]\ninner: {layers: [1]}\n")
    assert load_config(child, Outer) == Outer(seed=2, name="a", inner=Inner(lr=3.0, layers=(1,)))


def test_extends_paths_are_relative_to_the_file_naming_them(tmp_path, monkeypatch):
    write(tmp_path / "lib" / "root.yaml", "name: root\n")
    write(tmp_path / "lib" / "mid.yaml", "extends: root.yaml\nseed: 5\n")  # lib/, not cwd
    child = write(tmp_path / "exp" / "deep" / "child.yaml", "extends: ../../lib/mid.yaml\n")
    monkeypatch.chdir(tmp_path / "exp")
    assert load_config(child, Outer) == Outer(seed=5, name="root")


def test_extends_chain_and_diamond(tmp_path):
    write(tmp_path / "d.yaml", "name: d\nseed: 1\n")
    write(tmp_path / "b.yaml", "extends: d.yaml\nseed: 2\n")
    write(tmp_path / "c.yaml", "extends: d.yaml\ninner: {lr: 4}\n")
    top = write(tmp_path / "a.yaml", "extends: [b.yaml, c.yaml]\n")
    assert load_config(top, Outer) == Outer(seed=1, name="d", inner=Inner(lr=4.0))  # c re-sets d


@pytest.mark.parametrize("files, match", [
    ({"a.yaml": "extends: a.yaml\n"}, r"a\.yaml: extends cycle \(a\.yaml -> a\.yaml\)"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "extends: a.yaml\n"},
     r"a\.yaml: extends cycle \(a\.yaml -> b\.yaml -> a\.yaml\)"),
    ({"a.yaml": "extends: nope.yaml\n"}, r"a\.yaml: extends: 'nope\.yaml': no such file"),
    ({"a.yaml": "extends: 5\n"}, r"a\.yaml: extends: expected a file or a list of files, got 5"),
    ({"a.yaml": "extends: [b.yaml, '']\n", "b.yaml": ""}, r"a\.yaml: extends: expected a file"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "sed: 1\n"}, r"b\.yaml: sed: unknown key"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "inner:\n  lr: 1\n  lr: 2\n"},
     r"b\.yaml: not valid YAML \(duplicate key 'lr'"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "x: &a 1\nseed: *a\n"},
     r"b\.yaml: not valid YAML \(aliases"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "- 1\n"},
     r"b\.yaml: expected a mapping at the top level"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "seed: -1\n"},
     r"a\.yaml: seed: must be >= 0, got -1 \(set in .*b\.yaml\)"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "inner: {lr: fast}\n"},
     r"a\.yaml: inner\.lr: expected a number, got 'fast' \(set in .*b\.yaml\)"),
    ({"a.yaml": "inner:\n  extends: b.yaml\n"}, r"a\.yaml: inner\.extends: unknown key"),
])
def test_extends_refusals_are_one_line_naming_the_file(tmp_path, files, match):
    for name, text in files.items():
        write(tmp_path / name, text)
    refused(tmp_path / "a.yaml", match)


def test_extended_files_get_the_size_check(tmp_path):
    write(tmp_path / "big.yaml", "name: " + "x" * (1 << 20) + "\n")
    refused(write(tmp_path / "a.yaml", "extends: big.yaml\n"), r"big\.yaml: too large")


def test_extends_depth_and_file_count_are_bounded(tmp_path):
    for k in range(MAX_EXTENDS_DEPTH + 2):
        write(tmp_path / f"c{k}.yaml", f"extends: c{k + 1}.yaml\n" if k <= MAX_EXTENDS_DEPTH
              else "seed: 3\n")
    refused(tmp_path / "c0.yaml", rf"c{MAX_EXTENDS_DEPTH}\.yaml: extends chain deeper than "
                                  rf"{MAX_EXTENDS_DEPTH} files")
    assert load_config(tmp_path / f"c{2}.yaml", Outer).seed == 3  # MAX_EXTENDS_DEPTH deep: fine
    names = [f"w{k}.yaml" for k in range(MAX_EXTENDS_FILES + 1)]
    for name in names:
        write(tmp_path / name, "")
    refused(write(tmp_path / "wide.yaml", f"extends: {json.dumps(names)}\n"),
            rf"composed of more than {MAX_EXTENDS_FILES} files")


def test_composed_mapping_has_no_extends_and_names_its_sources(tmp_path):
    write(tmp_path / "b.yaml", "seed: 2\ninner: {lr: 4}\n")
    top = write(tmp_path / "a.yaml", "extends: b.yaml\nname: a\n")
    merged, origin = compose_config(top, Outer, ["inner.lr=5.0"])
    assert merged == {"seed": 2, "inner": {"lr": 5.0}, "name": "a"}
    assert origin["seed"].endswith("b.yaml") and origin["name"].endswith("a.yaml")
    assert origin["inner.lr"] == "--set 'inner.lr=5.0'"


# --- --set --------------------------------------------------------------------------------


@pytest.mark.parametrize("token, key, value", [
    ("updates=5", "updates", 5), ("env.observation.leader=true", "env.observation.leader", True),
    ("ppo.learning_rate=0.0003", "ppo.learning_rate", 0.0003),
    ("scenes.files=[a.tfrecord, b.pkl]", "scenes.files", ["a.tfrecord", "b.pkl"]),
    ("env.max_steps=null", "env.max_steps", None), ("out_dir=runs=2", "out_dir", "runs=2"),
    (" seed = 7", "seed", 7),
])
def test_parse_override(token, key, value):
    assert parse_override(token) == (key, value)


@pytest.mark.parametrize("token, match", [
    ("updates", r"--set 'updates': expected KEY=VALUE"), ("=3", r"expected KEY=VALUE"),
    ("ppo..lr=1", r"expected KEY=VALUE"), ("scenes.files[0]=a", r"expected KEY=VALUE"),
    ("updates=", r"--set 'updates=': no value \(write updates=null for none\)"),
    ("updates=[1", r"--set 'updates=\[1': value is not valid YAML"),
    ("seed=*a", r"not valid YAML \(aliases"), ("extends=x.yaml", r"extends is not a setting"),
    ("x=" + "1" * 20000, r"longer than"),
])
def test_malformed_override_is_refused_naming_it(token, match):
    with pytest.raises(ConfigError, match=match) as info:
        parse_override(token)
    assert "\n" not in str(info.value)


def train_cli(capsys, *argv):
    """``magail-sumo train ARGV --print-config``: (exit code, printed config or None, stderr)."""
    from magail_sumo.cli.main import main

    code = main(["train", *argv, "--print-config"])
    out, err = capsys.readouterr()
    return code, (yaml.safe_load(out) if code == 0 else None), err


def test_train_set_changes_settings_and_records_them(capsys):
    demo = str(CONFIGS / "demo.yaml")
    code, cfg, _ = train_cli(capsys, "--config", demo, "--set", "updates=1",
                             "--set", "env.observation.leader=true", "--set",
                             "scenes.files=[data/womd/850c48d8bbfa008f.tfrecord]",
                             "--set", "discriminator.transformer={embed_dim: 16, num_heads: 2}",
                             "--seed", "3")
    assert code == 0
    assert (cfg["updates"], cfg["seed"], cfg["env"]["observation"]["leader"]) == (1, 3, True)
    assert cfg["scenes"]["files"] == ["data/womd/850c48d8bbfa008f.tfrecord"]
    assert cfg["discriminator"]["transformer"]["embed_dim"] == 16
    assert cfg["discriminator"]["transformer"]["num_layers"] == 1  # the rest of the map kept
    want = flat(json.loads((RESOLVED / "demo.json").read_text())) | DEMO_MOVED
    changed = {"updates", "seed", "env.observation.leader", "scenes.files",
               "discriminator.transformer.embed_dim"}
    assert {k: v for k, v in flat(cfg).items() if k not in changed} == \
        {k: v for k, v in {**want, **ADDED_SINCE}.items() if k not in changed}
    # later --set win; --set scenes.split / part take the scenes from a split
    code, cfg, _ = train_cli(capsys, "--config", demo, "--set", "updates=2", "--set", "updates=4",
                             "--set", f"scenes.split={SPLIT}", "--set", "scenes.part=test")
    assert code == 0 and cfg["updates"] == 4
    assert cfg["scenes"]["files"] == list(load_split(SPLIT).test)


@pytest.mark.parametrize("token, match", [
    ("ppo.foo=1", r"--set 'ppo\.foo=1': ppo\.foo: unknown key \(known: batch_size"),
    ("nope=1", r"--set 'nope=1': nope: unknown key"),
    ("env={foo: 1}", r"--set 'env=\{foo: 1\}': env\.foo: unknown key"),
    ("updates=-1", r"demo\.yaml: updates: must be >= 0, got -1 \(from --set 'updates=-1'\)"),
    ("ppo.gamma=1.5", r"ppo\.gamma: must be in \[0, 1\], got 1\.5 \(from --set 'ppo\.gamma=1\.5'\)"),
    ("seed=4294967296", r"seed: must be in \[0, 2\*\*32\)"),
    ("env.observation.leader=maybe", r"env\.observation\.leader: expected true or false"),
    ("ppo.learning_rate=3e-4",
     r"ppo\.learning_rate: expected a number, got '3e-4' \(YAML reads it as text: write 0\.0003\)"),
    ("ppo.learning_rate=1e-12",  # the hint itself must be a float to YAML 1.1
     r"got '1e-12' \(YAML reads it as text: write 1\.0e-12\)"),
    ("updates.x=1", r"updates: expected an integer, got \{'x': 1\} \(from --set 'updates\.x=1'\)"),
    ("scenes.part=test", r"scenes\.part: needs split next to it"),
    ("scenes.split=nope.yaml", r"--set 'scenes\.split=nope\.yaml': scenes\.split: nope\.yaml: "
                               r"no such file"),
    ("updates", r"--set 'updates': expected KEY=VALUE"),
])
def test_train_set_refusals_name_the_key(capsys, token, match):
    import re

    code, _, err = train_cli(capsys, "--config", str(CONFIGS / "demo.yaml"), "--set", token)
    assert code == 1 and err.count("\n") == 1 and re.search(match, err), err


# --- scenes from a split ------------------------------------------------------------------


def test_split_scenes_are_the_old_file_lists():
    train = list(load_split(SPLIT).train)
    for old in ("womd14_magail", "sac_task", "gameformer"):
        assert json.loads((RESOLVED / f"{old}.json").read_text())["scenes"]["files"] == train
    city = json.loads((RESOLVED / "city_ingolstadt21.json").read_text())["scenes"]["files"]
    assert city == ["data/sumo/ingolstadt21", *train]
    cfg = load_config(CONFIGS / "scenes" / "womd14_train.yaml", TrainConfig)
    assert list(cfg.scenes.files) == train and cfg.scenes.networks == "out/networks"
    assert list(load_config(CONFIGS / "scenes" / "ingolstadt21_womd14_train.yaml",
                            TrainConfig).scenes.files) == city


def test_split_path_is_relative_to_the_file_and_parts(tmp_path, monkeypatch):
    split = load_split(SPLIT)
    write(tmp_path / "splits" / "s.yaml", SPLIT.read_text())
    cfg = write(tmp_path / "exp" / "c.yaml", "scenes:\n  files: [x.tfrecord]\n"
                                             "  split: ../splits/s.yaml\n  part: test\n")
    monkeypatch.chdir(tmp_path / "splits")  # not where the config is
    assert list(load_config(cfg, TrainConfig).scenes.files) == ["x.tfrecord", *split.test]
    write(tmp_path / "exp" / "d.yaml", "scenes:\n  split: ../splits/s.yaml\n")  # part: train
    assert list(load_config(tmp_path / "exp" / "d.yaml", TrainConfig).scenes.files) == \
        list(split.train)
    # a later file's files replace the split's, and the other way round
    write(tmp_path / "exp" / "e.yaml", "extends: d.yaml\nscenes: {files: [y.pkl]}\n")
    assert load_config(tmp_path / "exp" / "e.yaml", TrainConfig).scenes.files == ("y.pkl",)
    # programmatic: relative to the working directory
    assert from_dict(ScenesConfig, {"split": "s.yaml", "part": "test"}).files == split.test


@pytest.mark.parametrize("text, match", [
    ("scenes:\n  part: train\n", r"c\.yaml: scenes\.part: needs split next to it"),
    ("scenes:\n  split: nope.yaml\n", r"c\.yaml: scenes\.split: .*nope\.yaml: no such file"),
    ("scenes:\n  split: s.yaml\n  part: valid\n",
     r"c\.yaml: scenes\.part: must be one of train, test, got 'valid'"),
    ("scenes:\n  split: [s.yaml]\n", r"c\.yaml: scenes\.split: expected a split file"),
    ("scenes:\n  split: s.yaml\n  files: x.pkl\n", r"c\.yaml: scenes\.files: expected a list"),
    ("scenes:\n  split: bad.yaml\n", r"c\.yaml: scenes\.split: .*bad\.yaml: train: needs at least"),
])
def test_bad_split_scenes_are_refused_naming_the_key(tmp_path, text, match):
    write(tmp_path / "s.yaml", SPLIT.read_text())
    write(tmp_path / "bad.yaml", "train: []\ntest: [a.pkl]\n")
    refused(write(tmp_path / "c.yaml", text), match, cls=TrainConfig)


# --- the run record -----------------------------------------------------------------------


def test_run_record_holds_the_resolved_config(tmp_path):
    path = CONFIGS / MOVED["womd14_decomposed_social_leader_edge_guard_eol"]
    cfg = load_config(path, TrainConfig, ["updates=3"])
    run = record_run(tmp_path / "run", cfg)
    text = (run / "config.yaml").read_text()
    assert "extends" not in text and "split" not in text
    recorded = yaml.safe_load(text)
    assert flat(recorded) == resolved(path, ["updates=3"])
    want = flat(json.loads((RESOLVED / "womd14_decomposed_social_leader_edge_guard_eol.json")
                           .read_text()))
    assert flat(recorded) == {**want, **ADDED_SINCE, "updates": 3}
    assert load_config(run / "config.yaml", TrainConfig) == cfg  # a plain config: loads as is


def test_extends_naming_a_fifo_says_so(tmp_path):
    """A FIFO named by ``extends:`` is refused as one (it was called missing), at once."""
    import os

    os.mkfifo(tmp_path / "base.yaml")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("extends: base.yaml\n")
    with pytest.raises(ConfigError, match=r"c.yaml: extends: 'base.yaml': is a FIFO"):
        load_config(cfg, TrainConfig)


def _extends_depth(path: Path) -> int:
    ext = yaml.safe_load(path.read_text()).get("extends") or []
    ext = [ext] if isinstance(ext, str) else ext
    return 1 + max((_extends_depth((path.parent / e).resolve()) for e in ext), default=0)


def test_published_configs_leave_room_to_extend():
    """A user's variant of any published config (and variants of it) still composes: no
    published chain is more than half the depth bound (route_idm_gwc_speed.yaml reached 16,
    the old bound, so a config extending it was refused)."""
    for path in EXPERIMENTS:
        assert _extends_depth(path) <= MAX_EXTENDS_DEPTH // 2, path
