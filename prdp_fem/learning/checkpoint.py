r"""Saved, resumable training: a training's whole state in Orbax checkpoints.

:func:`~prdp_fem.learning.learned.train` and :func:`~prdp_fem.learning.heat.train` take
``checkpoints=Checkpoints(directory, every=N)``: after every ``N``-th epoch and after the last
one they save

* the model's ``params`` (its own item: :func:`load_params` reads it alone, for predictions),
* the optimiser state and the refinement controller's state,
* the host state: the shuffling RNG, the epoch records so far, the cumulative CG iterations,
  optimiser steps and run time,

so that ``Checkpoints(directory, resume=True)`` continues from the last checkpoint with the
same result, bit for bit, as a run that was never interrupted (the records' run times are wall
clock and differ). A save is atomic (Orbax writes a temporary directory and renames it), so a
run killed while saving resumes from the checkpoint before.

A checkpoint directory belongs to one training: its *kind* (``"learned"``, ``"heat"``), the
checkpoint format, the prdp_fem version, and ``metadata`` -- JSON facts its caller names it by
(a scene's fingerprint, the data split). Resuming or loading with any of them different is
refused (:class:`~prdp_fem.errors.CheckpointError`), as is a model or optimiser whose state
does not have the saved shapes, and a fresh run into a directory that holds checkpoints.

>>> import tempfile
>>> Checkpoints(tempfile.mkdtemp(), every=5).every
5
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .._version import __version__
from ..errors import CheckpointError

__all__ = ["FORMAT", "CheckpointSession", "Checkpoints", "TrainingState", "load_params",
           "read_metadata", "start_state"]

#: The layout of a checkpoint (items and what they hold); another value is refused.
FORMAT = 1


@dataclasses.dataclass(frozen=True)
class Checkpoints:
    """Where and how often a training saves itself.

    ``directory`` (made absolute here; created on the first save), ``every``: save after
    epochs ``every, 2 every, ...`` and after the last; ``keep``: how many of the latest
    checkpoints stay (older ones are deleted when a new one lands); ``resume``: continue from
    the latest checkpoint in ``directory`` (none there: start from epoch 1); ``metadata``:
    JSON facts stored with the checkpoints and required equal on resume and load.
    """

    directory: str | Path
    every: int = 10
    keep: int = 2
    resume: bool = False
    metadata: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        for name in ("every", "keep"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise CheckpointError(f"checkpoints: {name}={value!r}; expected an integer "
                                      ">= 1")
        if not isinstance(self.resume, bool):
            raise CheckpointError(f"checkpoints: resume={self.resume!r}; expected True or False")
        try:
            metadata = json.loads(json.dumps(dict(self.metadata), allow_nan=False))
        except (TypeError, ValueError) as error:
            raise CheckpointError(f"checkpoints: metadata is not plain JSON ({error}); expected "
                                  "strings, numbers, lists and dicts") from None
        object.__setattr__(self, "metadata", metadata)
        # Orbax requires an absolute path (a relative one fails inside its save)
        object.__setattr__(self, "directory", Path(self.directory).expanduser().absolute())


class TrainingState(NamedTuple):
    """Everything a training loop carries from one epoch to the next."""

    epoch: int              # the last finished epoch (0: none)
    params: Any             # the model's trainable pytree
    opt_state: Any          # the optax state
    control: Any            # the refinement controller's state
    rng: dict               # ``numpy.random.Generator.bit_generator.state``
    records: list           # the epoch records so far (NamedTuples)
    counters: dict          # cumulative host tallies: primal, adjoint, validation, steps,
    #                         run_time (validation: absent from older checkpoints, read as 0)


def start_state(session: CheckpointSession | None, params, opt_state, control,
                rng: np.random.Generator, record_type, epochs: int,
                callback=None) -> TrainingState:
    """The state a training starts from: epoch 0 with the given ``params``, ``opt_state``
    and ``control`` (templates of a checkpoint's arrays), or the latest checkpoint of a
    resumed ``session`` -- then ``rng`` takes its state and ``callback`` gets its records."""
    fresh = TrainingState(0, params, opt_state, control, rng.bit_generator.state, [],
                          {"primal": 0, "adjoint": 0, "steps": 0, "run_time": 0.0})
    restored = None if session is None else session.restore(fresh, record_type, epochs)
    if restored is None:
        return fresh
    rng.bit_generator.state = restored.rng
    if callback is not None:
        for record in restored.records:
            callback(record)
    return restored


def _orbax():
    import orbax.checkpoint as ocp  # here, not at import: it loads hundreds of modules

    return ocp


def _header(kind: str, metadata: Mapping[str, Any]) -> dict:
    return {"format": FORMAT, "kind": kind, "prdp_fem": __version__, "metadata": dict(metadata)}


def _manager(directory: Path, header: dict | None, *, every: int = 1, keep: int = 1):
    """Orbax's manager of ``directory``; ``header`` is written once, when it is created (a
    directory that has one keeps it: what :func:`_check_header` compares)."""
    ocp = _orbax()
    from orbax.checkpoint import checkpoint_managers

    options = ocp.CheckpointManagerOptions(
        save_decision_policy=checkpoint_managers.FixedIntervalPolicy(every),
        preservation_policy=checkpoint_managers.LatestN(keep),
        # a save returns once it is on disk: nothing is lost when the process ends
        enable_async_checkpointing=False, cleanup_tmp_directories=True)
    handlers = {"params": ocp.StandardCheckpointHandler(),
                "state": ocp.StandardCheckpointHandler(), "host": ocp.JsonCheckpointHandler()}
    return ocp.CheckpointManager(directory, options=options, item_handlers=handlers,
                                 metadata=header)


def _check_fits(manager, directory: Path, step: int, templates: Mapping[str, Any],
                what: str) -> None:
    """Refuse a checkpoint whose arrays are not the templates' (their count and shapes; as
    multisets, since Orbax's metadata orders a NamedTuple's fields by name), before Orbax
    reads it: a restore that fails half way leaves its reads behind."""
    import jax

    saved = manager.item_metadata(step)
    for name, template in templates.items():
        stored = sorted(tuple(leaf.shape) for leaf in jax.tree.leaves(saved[name].tree))
        wanted = sorted(tuple(np.shape(leaf)) for leaf in jax.tree.leaves(template))
        if stored != wanted:
            raise CheckpointError(
                f"{directory}: checkpoint {step} holds {name} of {len(stored)} arrays "
                f"{_short(stored)}; this {what} has {len(wanted)} {_short(wanted)} (expected "
                "the model and optimiser it was saved from)")


def _check_header(manager, directory: Path, kind: str, metadata: Mapping[str, Any]) -> None:
    stored = manager.metadata().custom_metadata or {}
    wanted = _header(kind, metadata)
    for key, what in (("format", "checkpoint format"), ("kind", "training"),
                      ("prdp_fem", "prdp_fem version"), ("metadata", "metadata")):
        if stored.get(key) != wanted[key]:
            raise CheckpointError(
                f"{directory}: holds checkpoints of another {what} ({key} = "
                f"{_short(stored.get(key))}); expected {_short(wanted[key])}")


def _short(value) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 160 else text[:157] + "..."


def _steps(directory: Path) -> list[int]:
    """The finished checkpoints in ``directory`` (Orbax's step directories), oldest first."""
    if not directory.is_dir():
        return []
    return sorted(int(p.name) for p in directory.iterdir() if p.is_dir() and p.name.isdigit()
                  and (p / "commit_success.txt").exists())


class CheckpointSession:
    """One training's checkpoints, open (:meth:`open`, a context manager)."""

    def __init__(self, checkpoints: Checkpoints, kind: str, manager):
        self.checkpoints, self.kind, self._manager = checkpoints, kind, manager

    @classmethod
    @contextlib.contextmanager
    def open(cls, checkpoints: Checkpoints | None, kind: str) -> Iterator[CheckpointSession | None]:
        """The session of ``checkpoints`` (``None``: no checkpoints, yields ``None``)."""
        if checkpoints is None:
            yield None
            return
        if not isinstance(checkpoints, Checkpoints):
            raise CheckpointError(f"checkpoints={checkpoints!r}: expected a "
                                  "prdp_fem.learning.Checkpoints(directory, every=...)")
        directory = checkpoints.directory
        if directory.exists() and not directory.is_dir():
            raise CheckpointError(f"{directory}: not a directory; expected a checkpoint "
                                  "directory")
        if _steps(directory) and not checkpoints.resume:
            raise CheckpointError(f"{directory}: holds checkpoints already; pass resume=True "
                                  "(--resume) to continue that training or choose another "
                                  "directory")
        manager = _manager(directory, _header(kind, checkpoints.metadata),
                           every=checkpoints.every, keep=checkpoints.keep)
        try:
            if _steps(directory):
                _check_header(manager, directory, kind, checkpoints.metadata)
            yield cls(checkpoints, kind, manager)
        finally:
            manager.close()

    def restore(self, template: TrainingState, record_type, epochs: int) -> TrainingState | None:
        """The latest checkpoint's state shaped like ``template`` (``None`` when there is
        none); refused when it is past ``epochs`` or its arrays do not fit the template."""
        ocp = _orbax()
        step = self._manager.latest_step()
        if step is None:
            return None
        directory = self.checkpoints.directory
        if step > epochs:
            raise CheckpointError(f"{directory}: the latest checkpoint is of epoch {step}; "
                                  f"expected at most epochs={epochs} (train longer or start "
                                  "afresh in another directory)")
        state = {"opt_state": template.opt_state, "control": template.control}
        _check_fits(self._manager, directory, step, {"params": template.params,
                                                     "state": state}, "training")
        restored = self._manager.restore(step, args=ocp.args.Composite(
            params=ocp.args.StandardRestore(template.params),
            state=ocp.args.StandardRestore(state), host=ocp.args.JsonRestore()))
        host = restored["host"]
        return TrainingState(step, restored["params"], restored["state"]["opt_state"],
                             restored["state"]["control"], host["rng"],
                             [record_type(**r) for r in host["records"]], host["counters"])

    def save(self, state: TrainingState, *, final: bool) -> None:
        """Save ``state`` if its epoch is due (every ``every``-th, or ``final``)."""
        ocp = _orbax()
        if not (final or self._manager.should_save(state.epoch)):
            return
        host = {"rng": state.rng, "records": [_plain(r._asdict()) for r in state.records],
                "counters": _plain(state.counters)}
        self._manager.save(state.epoch, args=ocp.args.Composite(
            params=ocp.args.StandardSave(state.params),
            state=ocp.args.StandardSave({"opt_state": state.opt_state,
                                         "control": state.control}),
            host=ocp.args.JsonSave(host)), force=final)


def _plain(values: Mapping[str, Any]) -> dict:
    """Record fields as JSON numbers (NumPy scalars are not JSON; NaN is written as NaN)."""
    out = {}
    for key, value in values.items():
        if isinstance(value, np.generic):
            value = value.item()
        out[key] = value
    return out


def read_metadata(directory: str | Path) -> dict:
    """What a checkpoint directory was saved as: ``{"format", "kind", "prdp_fem",
    "metadata", "epochs"}`` (``epochs``: its checkpoints, oldest first)."""
    directory = Path(directory).expanduser().absolute()
    steps = _steps(directory)
    if not steps:
        raise CheckpointError(f"{directory}: holds no finished checkpoint; expected the "
                              "directory a training saved into")
    manager = _manager(directory, None)
    try:
        stored = manager.metadata().custom_metadata or {}
    finally:
        manager.close()
    return {**stored, "epochs": steps}


def load_params(directory: str | Path, params, *, kind: str, metadata: Mapping[str, Any],
                epoch: int | None = None) -> tuple[Any, int]:
    """The model parameters saved in ``directory`` (its latest checkpoint, or ``epoch``'s),
    shaped like ``params``; refused unless the directory was saved by a ``kind`` training
    with ``metadata``, this checkpoint format and prdp_fem version. Returns ``(params,
    epoch)``."""
    directory = Path(directory).expanduser().absolute()
    steps = _steps(directory)
    if not steps:
        raise CheckpointError(f"{directory}: holds no finished checkpoint; expected the "
                              "directory a training saved into")
    if epoch is not None and epoch not in steps:
        raise CheckpointError(f"{directory}: no checkpoint of epoch {epoch}; expected one of "
                              f"{steps}")
    step = steps[-1] if epoch is None else epoch
    ocp = _orbax()
    manager = _manager(directory, _header(kind, metadata))
    try:
        _check_header(manager, directory, kind, metadata)
        _check_fits(manager, directory, step, {"params": params}, "model")
        restored = manager.restore(step, args=ocp.args.Composite(
            params=ocp.args.StandardRestore(params)))
    finally:
        manager.close()
    return restored["params"], step

