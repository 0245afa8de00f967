"""Pretrained policies shipped with magail_sumo: ``magail-sumo evaluate --policy pretrained[:NAME]``.

The registry is a folder (this package's folder; ``$MAGAIL_SUMO_PRETRAINED_DIR`` or a ``root``
argument replaces it) holding, per policy ``NAME``:

* ``NAME.pt`` — a ``magail-sumo train`` checkpoint (format ``magail_sumo.checkpoint/2``, read with
  ``torch.load(weights_only=True)``; :func:`export` keeps only what evaluation needs: the
  policy with its observation normaliser, the run config and the update count);
* ``NAME.json`` — its card, a JSON object: ``name``, ``description``, ``checkpoint`` (``file``,
  ``sha256`` of ``NAME.pt``, ``source``, ``update``), ``config`` (the training config),
  ``split`` (the split file and its ``train`` / ``test`` files, or null) and ``figures`` (e.g.
  the rows of ``benchmarks/quality.py --json``, or null), and optionally ``sampling``
  (``{"noise_scale": k, "note": how k was chosen}``: evaluation samples the policy with noise
  scale ``k`` unless ``--noise-scale`` says otherwise; absent or null: 1; optionally also
  ``"noise_weights"`` and ``"noise_correlation"``, one number per action: the noise's shape,
  :mod:`magail_sumo.agents.noise`, kept whatever ``--noise-scale`` says).

and one ``index.json``, ``{"default": NAME}`` (or ``null``): the policy ``pretrained`` alone
means. ``NAME`` is a file name of ``[A-Za-z0-9._-]`` (not starting with ``.``) and not the name
of a built-in method. A policy is available when both its files are there; a card whose
``sha256`` does not match its checkpoint is refused. Every failure is one
:class:`PretrainedError` line naming the spec and, for an unknown name, the available ones.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

from magail_sumo.inputs import InputFileError, open_regular
from magail_sumo.agents.base import check_noise_scale
from magail_sumo.agents.noise import NoiseShape
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import atomic_paths, inside, is_safe_name, printable
from magail_sumo.splits import load_split, scene_stem

#: environment variable naming another registry folder (tests, a user's own policies)
ENV_VAR = "MAGAIL_SUMO_PRETRAINED_DIR"
#: the ``--policy`` word
PREFIX = "pretrained"
INDEX = "index.json"
CARD_FORMAT = "magail_sumo.pretrained/1"
#: largest card or index read (bytes)
MAX_CARD_BYTES = 1 << 20
#: names a pretrained policy may not take (``evaluate``'s built-in methods)
RESERVED = ("logreplay", "constvel", "sumo", "random", PREFIX)


class PretrainedError(MagailSumoError):
    """A pretrained policy spec that cannot be resolved (one line)."""


@dataclass(frozen=True)
class Pretrained:
    """A resolved registry entry: ``checkpoint`` (``NAME.pt``) and its parsed ``card``."""

    name: str
    checkpoint: Path
    card: dict[str, Any]


def registry_dir(root: str | PathLike | None = None) -> Path:
    """The registry folder: ``root``, else ``$MAGAIL_SUMO_PRETRAINED_DIR`` (when set and not
    empty), else this package's folder."""
    if root is not None:
        return Path(root)
    env = os.environ.get(ENV_VAR, "")
    return Path(env) if env else Path(__file__).resolve().parent


def is_pretrained_spec(spec: str) -> bool:
    """True for ``pretrained`` and ``pretrained:NAME``."""
    return spec == PREFIX or spec.startswith(PREFIX + ":")


def available(root: str | PathLike | None = None) -> list[str]:
    """Sorted names with both ``NAME.pt`` and ``NAME.json`` in the registry folder."""
    d = registry_dir(root)
    if not d.is_dir():
        return []
    return sorted(p.stem for p in d.glob("*.pt")
                  if is_safe_name(p.stem) and p.is_file() and p.with_suffix(".json").is_file())


def _read_json(path: Path, what: str) -> Any:
    """The JSON value of ``path`` (at most :data:`MAX_CARD_BYTES`); :class:`PretrainedError`
    naming ``path`` and the problem when it cannot be read, is larger, is not UTF-8 JSON or is
    nested too deep to parse."""
    try:  # a regular file only: a FIFO would block, a device stream
        with open_regular(path, expected=f"a {what}") as fh:
            raw = fh.read(MAX_CARD_BYTES + 1)
    except InputFileError as exc:
        raise PretrainedError(f"{path}: cannot read the {what} ({exc.problem})") from None
    except OSError as exc:
        raise PretrainedError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    if len(raw) > MAX_CARD_BYTES:
        raise PretrainedError(f"{path}: {what} larger than {MAX_CARD_BYTES} bytes")
    try:
        return json.loads(raw.decode("utf-8"))
    except RecursionError:
        raise PretrainedError(f"{path}: {what} is nested too deep") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise PretrainedError(f"{path}: {what} is not JSON ({printable(str(exc), 100)})") from None


def read_figures(path: str | PathLike) -> Any:
    """A figures file for :func:`export` (JSON, e.g. ``benchmarks/quality.py --json``);
    :class:`PretrainedError` naming it when it cannot be read or is not JSON."""
    return _read_json(Path(path), "figures file")


def default_name(root: str | PathLike | None = None) -> str | None:
    """The name ``index.json`` gives as ``default`` (None when there is no index or it names
    none)."""
    path = registry_dir(root) / INDEX
    if not path.is_file():
        return None
    index = _read_json(path, "index")
    if not isinstance(index, dict) or not isinstance(index.get("default"), (str, type(None))):
        raise PretrainedError(f"{path}: index must be a JSON object with \"default\": a name "
                              "or null")
    return index["default"]


def _listing(root: str | PathLike | None) -> str:
    names = available(root)
    return f"available: {', '.join(names) if names else 'none'}; folder {registry_dir(root)}"


def name_of(spec: str, root: str | PathLike | None = None) -> str:
    """The registry name a ``pretrained[:NAME]`` spec means (``pretrained``: the default)."""
    if not is_pretrained_spec(spec):
        raise PretrainedError(f"{printable(spec, 80)}: not a pretrained spec "
                              f"({PREFIX} or {PREFIX}:NAME)")
    name = spec[len(PREFIX) + 1:] if spec != PREFIX else default_name(root)
    if name is None:
        raise PretrainedError(f"{spec}: no default pretrained policy ({INDEX} names none; "
                              f"give {PREFIX}:NAME; {_listing(root)})")
    if not is_safe_name(name) or name in RESERVED:
        raise PretrainedError(f"{printable(spec, 80)}: {printable(name, 60)!r} is not a "
                              "pretrained policy name ([A-Za-z0-9._-], not a built-in "
                              f"method's name; {_listing(root)})")
    return name


def sha256(path: str | PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def resolve(spec: str, root: str | PathLike | None = None) -> Pretrained:
    """The registry entry of ``pretrained`` / ``pretrained:NAME``.

    :raises PretrainedError: no default, a bad or unknown name (listing the available ones),
        a missing card, a card that is not a JSON object or whose ``sha256`` does not match
        the checkpoint.
    """
    name = name_of(spec, root)
    d = registry_dir(root)
    ckpt, card_path = d / f"{name}.pt", d / f"{name}.json"
    if not ckpt.is_file():
        raise PretrainedError(f"{spec}: unknown pretrained policy {name!r} ({_listing(root)})")
    if not card_path.is_file():
        raise PretrainedError(f"{spec}: {card_path}: card missing beside {ckpt.name} "
                              f"({_listing(root)})")
    card = _read_json(card_path, "card")
    if not isinstance(card, dict):
        raise PretrainedError(f"{card_path}: card must be a JSON object")
    rec = card.get("checkpoint")
    want = rec.get("sha256") if isinstance(rec, dict) else None
    if want is not None and want != sha256(ckpt):
        raise PretrainedError(f"{spec}: {ckpt}: sha256 differs from its card's (the "
                              "checkpoint was replaced; export it again)")
    return Pretrained(name, ckpt, card)


def export(checkpoint: str | PathLike, name: str, root: str | PathLike | None = None, *,
           description: str = "", split: str | PathLike | None = None,
           figures: Any = None, make_default: bool = False,
           noise_scale: float | None = None, noise_note: str = "",
           noise_shape: NoiseShape | None = None) -> Pretrained:
    """Add a training checkpoint to a registry folder as ``NAME.pt`` + ``NAME.json``.

    The checkpoint is read safely and written back with only the policy, the run config and
    the update count (what evaluation loads; no optimiser, discriminator or RNG state). With
    ``split`` (a split file, :mod:`magail_sumo.splits`) the card records it, and a
    checkpoint whose config trains on one of its test scenes (same file name stem) is refused.
    ``make_default`` names it in ``index.json``. ``noise_scale`` (with ``noise_note``, how it
    was chosen, and ``noise_shape``, the noise's weights and correlation when not plain) is the
    card's ``sampling``. Every argument is checked before anything is
    written; then ``NAME.pt``, ``NAME.json`` (and ``index.json``) are written to temporary files
    and replace the old ones only once all are written
    (:func:`~magail_sumo.outputs.atomic_paths`): a bad argument, a crash or a full disk leaves
    the registered policy as it was, its card's checksum matching.
    """
    # lazy: reading the registry (the report's workers, the CLI) needs no torch; export does
    from magail_sumo.training.checkpoints import load_checkpoint, write_state

    if not is_safe_name(name) or name in RESERVED:
        raise PretrainedError(f"{printable(name, 60)!r}: not a pretrained policy name "
                              "([A-Za-z0-9._-], not a built-in method's name)")
    sampling = None
    if noise_scale is not None:
        sampling = {"noise_scale": check_noise_scale(noise_scale, "--noise-scale"),
                    "note": noise_note}
        if noise_shape is not None and not noise_shape.plain:
            sampling.update(noise_weights=list(noise_shape.weights),
                            noise_correlation=list(noise_shape.correlation))
    elif noise_shape is not None and not noise_shape.plain:
        raise PretrainedError("a noise shape needs its noise scale (--noise-scale)")
    state = load_checkpoint(checkpoint)
    split_rec = None
    if split is not None:
        sp = load_split(split)
        scenes = state["config"].get("scenes")
        files = scenes.get("files") if isinstance(scenes, dict) else None
        stems = {scene_stem(f): f for f in (files if isinstance(files, list) else [])
                 if isinstance(f, str)}
        both = [f for f in sp.test if scene_stem(f) in stems]
        if both:
            raise PretrainedError(f"{checkpoint}: trained on {stems[scene_stem(both[0])]}, a test "
                                  f"scene of {split} ({both[0]})")
        split_rec = {"file": str(split), "train": list(sp.train), "test": list(sp.test)}
    d = registry_dir(root)
    if d.exists() and not d.is_dir():
        raise PretrainedError(f"{d}: not a folder (the registry folder to export into)")
    d.mkdir(parents=True, exist_ok=True)
    ckpt = inside(d, f"{name}.pt")
    slim = {k: state[k] for k in ("format", "config", "policy", "update")}
    card = {"format": CARD_FORMAT, "name": name, "description": description,
            "checkpoint": {"file": ckpt.name, "sha256": None,
                           "source": str(checkpoint), "update": state["update"]},
            "config": state["config"], "split": split_rec, "figures": figures}
    if sampling is not None:
        card["sampling"] = sampling
    targets = [ckpt, inside(d, f"{name}.json")] + ([inside(d, INDEX)] if make_default else [])
    # every check above; the checkpoint, its card (and the index) replace the old ones together
    with atomic_paths(*targets) as tmps:
        with open(tmps[0], "wb") as fh:
            write_state(slim, fh)
        card["checkpoint"]["sha256"] = sha256(tmps[0])
        tmps[1].write_text(json.dumps(card, indent=2) + "\n", encoding="utf-8")
        if make_default:
            tmps[2].write_text(json.dumps({"default": name}, indent=2) + "\n", encoding="utf-8")
    return resolve(f"{PREFIX}:{name}", d)


__all__ = ["ENV_VAR", "PREFIX", "Pretrained", "PretrainedError", "available", "default_name",
           "export", "is_pretrained_spec", "name_of", "read_figures", "registry_dir", "resolve"]
