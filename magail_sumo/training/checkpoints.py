"""Checkpoint I/O of every training algorithm: safe reading, atomic writing, state encoding.

A checkpoint (``RUN/checkpoints/update_NNNNNN.pt`` and ``latest.pt``, written atomically by
:func:`save_checkpoint`) is a dict with at least ``format`` (:data:`CHECKPOINT_FORMAT`),
``config`` (the run's :class:`~magail_sumo.training.config.TrainConfig` as plain data),
``update`` and ``policy``; each algorithm adds its own state (see its module).

Checkpoints hold only tensors and plain data (dicts, lists, tuples, str, numbers, None) and are
read with ``torch.load(weights_only=True)`` (:func:`load_checkpoint`): a file cannot run code when
loaded. Numpy state (SB3's last observation and episode starts, the env's replayed actions, numpy
RNG states) is stored as tensors / lists (:func:`encode_state`, format
``magail_sumo.checkpoint/2``) and converted back on load, bit for bit. Format-1 checkpoints
(pickled numpy objects) are refused; a trusted one can be converted with
:func:`upgrade_checkpoint`.
"""

from __future__ import annotations

import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from magail_sumo.config import ConfigError, from_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import atomic_write, inside, inside_dir, one_line, printable

from .config import TrainConfig
from .rng import encode_rng

CHECKPOINT_FORMAT = "magail_sumo.checkpoint/2"
#: formats written by earlier versions (pickled numpy objects: unsafe to load)
OLD_CHECKPOINT_FORMATS = ("magail_sumo.checkpoint/1",)


class CheckpointError(MagailSumoError):
    """A checkpoint is missing, corrupt, or does not belong to the configured run."""


def pickle_mentions(p: Path, text: bytes) -> bool:
    """Whether the pickle inside torch zip file ``p`` contains ``text`` (read, never run)."""
    try:
        with zipfile.ZipFile(p) as z:
            name = next((n for n in z.namelist() if n.endswith("/data.pkl")), None)
            if name is None or z.getinfo(name).file_size > 1 << 26:
                return False
            return text in z.read(name)
    except (OSError, zipfile.BadZipFile, RuntimeError):
        return False


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint; :class:`CheckpointError` when missing, corrupt, unsafe or not one.

    Read with ``torch.load(weights_only=True)``: anything but tensors and plain data is refused
    before it is constructed (a crafted file cannot run code).
    """
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: checkpoint not found")
    try:
        with warnings.catch_warnings():  # torch warns about legacy (non-zip) files: our line says it
            warnings.simplefilter("ignore")
            state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means corrupt or unsafe
        if any(pickle_mentions(p, f.encode()) for f in OLD_CHECKPOINT_FORMATS):
            raise CheckpointError(
                f"{p}: checkpoint written by an older magail_sumo version in an unsafe format "
                "(pickled numpy objects); refused (convert a file you trust with "
                "magail-sumo train --upgrade-checkpoint FILE --trust)") from None
        found = re.search(r"GLOBAL ([\w.]+)|global[:\s]+([\w.]+)", str(exc))
        if found:
            raise CheckpointError(f"{p}: refused: the file holds {printable(found[1] or found[2], 80)}"
                                  ", not only tensors and plain data (not a magail_sumo "
                                  "checkpoint, or a crafted one)") from None
        # torch's own text advises weights_only=False, i.e. running the file's code: not here
        why = one_line(str(exc).split("Weights only load failed")[0].split(
            "(1) In PyTorch")[0], 200) or "the safe loader (weights_only) cannot read it"
        raise CheckpointError(f"{p}: corrupt or unreadable checkpoint ({type(exc).__name__}: "
                              f"{why}); refused, nothing in it was run") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{p}: not a magail_sumo checkpoint"
                              + (" (format " + printable(str(state.get("format")), 60) + ")"
                                 if isinstance(state, dict) and "format" in state else ""))
    missing = [k for k in ("config", "policy", "update") if k not in state]
    if missing:
        raise CheckpointError(f"{p}: checkpoint lacks {', '.join(missing)}")
    if not isinstance(state["config"], dict):
        raise CheckpointError(f"{p}: checkpoint config is not a mapping")
    if not isinstance(state["update"], int) or isinstance(state["update"], bool) \
            or state["update"] < 0:
        raise CheckpointError(f"{p}: checkpoint update is not a count "
                              f"({printable(repr(state['update']), 60)})")
    return state


def upgrade_checkpoint(path: str | Path, out: str | Path | None = None, *,
                       trust: bool = False) -> Path:
    """Convert a format-1 checkpoint to the current format (``out``, default: in place).

    Loading a format-1 file unpickles arbitrary objects, i.e. can run code the file holds:
    only for a file you trust, and only with ``trust=True``.
    """
    p = Path(path)
    if not trust:
        raise CheckpointError(f"{p}: converting a format-1 checkpoint runs the code it may "
                              "contain; only for a file you trust (--trust)")
    try:
        state = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{p}: corrupt or unreadable checkpoint ({type(exc).__name__}: "
                              f"{one_line(exc, 200)})") from None
    if not isinstance(state, dict) or state.get("format") not in OLD_CHECKPOINT_FORMATS:
        raise CheckpointError(f"{p}: not a format-1 magail_sumo checkpoint")
    try:
        state = encode_state(dict(state, format=CHECKPOINT_FORMAT))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(f"{p}: cannot convert ({type(exc).__name__}: "
                              f"{printable(str(exc), 200)})") from None
    dest = Path(out) if out is not None else p
    save_state(state, dest)
    return dest


def summarise_load_error(exc: BaseException) -> str:
    """One line for a ``load_state_dict`` error (torch's is a multi-line dump)."""
    text = str(exc)

    def keys(label: str) -> list[str]:
        m = re.search(label + r"[^:]*: ([^\n]*)", text)
        return re.findall(r'"([^"]*)"', m[1]) if m else []

    def some(names: list[str]) -> str:
        shown = ", ".join(printable(n, 60) for n in names[:4])
        return shown + (f" (+{len(names) - 4} more)" if len(names) > 4 else "")

    parts = []
    for label, what in (("Missing key", "missing keys"), ("Unexpected key", "unexpected keys")):
        found = keys(label)
        if found:
            parts.append(f"{what} {some(found)}")
    sizes = re.findall(r"size mismatch for ([^:]+):", text)
    if sizes:
        parts.append(f"size mismatch for {some(sizes)}")
    if parts:
        return "; ".join(parts)
    return f"{type(exc).__name__}: {printable(' '.join(text.split()), 200)}"


def load_into(obj: Any, state: Any, what: str, where: Path) -> None:
    """``obj.load_state_dict(state)``; a one-line :class:`CheckpointError` naming ``where``."""
    if not isinstance(state, dict):
        raise CheckpointError(f"{where}: checkpoint {what} is not a state dict")
    try:
        obj.load_state_dict(state)
    except Exception as exc:  # noqa: BLE001 - torch raises several kinds on a mismatch
        raise CheckpointError(f"{where}: checkpoint {what} does not fit this run "
                              f"({summarise_load_error(exc)})") from None


class _Sink:
    """A binary file for ``torch.save`` that keeps the ``OSError`` of a failed write: torch
    turns it into a RuntimeError of its own that names no file and no reason."""

    def __init__(self, fh) -> None:
        self.fh = fh
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self.fh.write(data)
        except OSError as exc:
            self.error = exc
            raise

    def flush(self) -> None:
        self.fh.flush()


def write_state(state: dict, fh) -> None:
    """``torch.save(state)`` into the open binary file ``fh``; a failed write (a full disk)
    is raised as its ``OSError`` (errno and reason), not as torch's RuntimeError."""
    sink = _Sink(fh)
    try:
        torch.save(state, sink)
    except RuntimeError:
        if sink.error is not None:
            raise sink.error from None
        raise


def save_state(state: dict, path: Path) -> None:
    """Write a checkpoint atomically (:func:`~magail_sumo.outputs.atomic_write`: a crash or a
    full disk leaves the old file or none); a failed write is an ``OSError`` naming ``path``
    and the reason (e.g. ``No space left on device``)."""
    with atomic_write(path, "wb") as fh:
        write_state(state, fh)


def save_checkpoint(run_dir: Path, state: dict, update: int) -> Path:
    """A run's checkpoint at ``update``: ``checkpoints/update_<update>.pt`` and, the same,
    ``checkpoints/latest.pt`` (both atomic); the first path. Both go through
    :func:`~magail_sumo.outputs.inside`: an :class:`~magail_sumo.outputs.OutputError` when
    ``checkpoints`` or a file in it is a symbolic link out of ``run_dir``."""
    inside_dir(run_dir, "checkpoints")
    path = inside(run_dir, "checkpoints", f"update_{update:06d}.pt")
    save_state(state, path)
    save_state(state, inside(run_dir, "checkpoints", "latest.pt"))
    return path


def checkpoint_config(state: dict, path: str | Path) -> TrainConfig:
    """The run config a checkpoint holds; :class:`CheckpointError` naming ``path`` if invalid."""
    try:
        return from_dict(TrainConfig, state["config"])
    except ConfigError as exc:
        raise CheckpointError(f"{path}: the checkpoint's config is invalid ({exc})") from None


def encode_state(state: dict) -> dict:
    """A run's state (numpy in places) as tensors and plain data (``torch.load``-safe)."""
    out = dict(state)
    out["rng"] = encode_rng(state["rng"])
    if "last_obs" in state:
        out["last_obs"] = torch.from_numpy(np.array(state["last_obs"]))
        out["last_episode_starts"] = torch.from_numpy(np.array(state["last_episode_starts"]))
        out["env_state"] = encode_env_state(state["env_state"])
        out["env_counters"] = [int(v) for v in state["env_counters"]]
        dt = dict(state["disc_trainer"])
        dt["rng"] = plain(dt["rng"])
        out["disc_trainer"] = dt
    return out


def plain(v: Any) -> Any:
    """Numpy scalars in nested dicts / lists as python ones (a numpy bit generator's state)."""
    if isinstance(v, dict):
        return {k: plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    return v.item() if isinstance(v, np.generic) else v


def tensor_field(v: Any, name: str) -> torch.Tensor:
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"{name} is not a tensor")
    return v


def encode_env_state(env_state) -> list:
    """:meth:`MultiSceneVecEnv.get_state` as tensors and plain data."""
    return [[int(ep), torch.from_numpy(np.stack(acts).astype(np.float32))
             if len(acts) else torch.zeros((0, 0), dtype=torch.float32)]
            for ep, acts in env_state]


def decode_env_state(venv, saved: Any) -> list[tuple[int, list[np.ndarray]]]:
    """A checkpoint's env state (:func:`encode_env_state`) as
    :meth:`MultiSceneVecEnv.set_state` takes it; ValueError / TypeError when it does not fit
    the env's scenes."""
    if not isinstance(saved, (list, tuple)) or len(saved) != len(venv.slots):
        raise ValueError(f"env_state does not hold {len(venv.slots)} scenes")
    out = []
    for k, (ep, acts) in enumerate(saved):
        acts = tensor_field(acts, "env_state actions")
        if not isinstance(ep, int) or not 0 <= ep < 1 << 31:
            raise ValueError(f"env_state scene {k}: bad episode index")
        if acts.numel() and (acts.dtype != torch.float32 or acts.dim() != 3
                             or tuple(acts.shape[1:]) != (venv.slots[k], 2)
                             or not bool(torch.isfinite(acts).all())):
            raise ValueError(f"env_state scene {k}: actions are not finite float32 "
                             f"(steps, {venv.slots[k]}, 2)")
        out.append((ep, list(acts.numpy()) if acts.numel() else []))
    return out
