"""What the commands share: progress bars, Ctrl-C between steps, tables, scene loading."""

from __future__ import annotations

import contextlib
import math
import signal
import sys
import threading
from pathlib import Path

from ..errors import SolverConfigError


class Interrupted(Exception):
    """Ctrl-C during a study: the message says where the finished records are."""


def is_interrupt(error: BaseException) -> bool:
    """Ctrl-C, also when it lands inside a JAX host callback (the iteration counter's taps):
    JAX re-raises it there wrapped in a ``JaxRuntimeError`` that names ``KeyboardInterrupt``."""
    return isinstance(error, KeyboardInterrupt) or (
        type(error).__name__ == "JaxRuntimeError" and "KeyboardInterrupt" in str(error))


class Bars:
    """tqdm bars over configurations and optimiser steps
    (:class:`prdp_fem.studies.runner.Progress`).

    Also where a requested stop (:func:`stop_between_steps`) takes effect: after a step's
    record is written, when a run finishes, and before the next one starts (a benchmark's
    next study included), in the main thread, outside any JAX computation.
    """

    def __init__(self, total: int):
        from tqdm import tqdm

        self._tqdm = tqdm
        self._quiet = not sys.stderr.isatty()
        self._outer = tqdm(total=total, desc="configurations", position=0,
                           disable=self._quiet, leave=True)
        self._inner = None
        self.stop_requested = False
        self.skipped = 0  # runs found done already (a resumed study), not run again

    def run_started(self, name: str, steps: int) -> None:
        self.stop_if_requested()  # a stop asked for between two runs: before this one builds
        self._inner = self._tqdm(total=steps, desc=name[:28], position=1, leave=False,
                                 disable=self._quiet)

    def step(self) -> None:
        if self._inner is not None:
            self._inner.update()
        self.stop_if_requested()

    def run_finished(self, name: str, skipped: bool) -> None:
        if self._inner is not None:
            self._inner.close()
            self._inner = None
        self._outer.update()
        if skipped:
            self.skipped += 1
            self._outer.write(f"{name}: done already, skipped")
        self.stop_if_requested()

    def stop_if_requested(self) -> None:
        """Stop here (``KeyboardInterrupt``) if a Ctrl-C asked for it: between two steps, or
        two studies of a benchmark."""
        if self.stop_requested:
            raise KeyboardInterrupt

    def close(self) -> None:
        self._outer.close()


def scene_for(name_or_path: str, steps: int | None, seed: int | None = None):
    """The scene, with ``--steps`` (optimiser steps, or a learned or heat study's epochs) and
    ``--seed`` (the seed of the data a learned or heat scene draws) set."""
    from ..scene.spec import load_scene, with_overrides

    scene = load_scene(name_or_path)
    if seed is not None:
        from ..bench.learning import seeded_scene

        scene = seeded_scene(scene, seed, f"--seed {seed}")
    if steps is not None:
        if steps < 0:
            raise SolverConfigError(f"--steps {steps}: expected an integer >= 0")
        kind = scene.study.kind
        if kind in ("learned", "heat"):  # learned and heat studies count epochs
            if steps < 1:
                raise SolverConfigError(f"--steps {steps}: a {kind} study's epochs; "
                                        "expected an integer >= 1")
            scene = with_overrides(scene, {kind: {"epochs": steps}})
        else:
            scene = with_overrides(scene, {"optimizer": {"steps": steps}})
    return scene


def fresh_directory(stem: str) -> Path:
    path, number = Path(stem), 2
    while path.exists() and any(path.iterdir()):
        path, number = Path(f"{stem}-{number}"), number + 1
    return path


def format_cell(value) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def print_table(rows: list[dict], columns: list[str]) -> None:
    cells = [[format_cell(row.get(c, "")) for c in columns] for row in rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(columns)]
    print("  ".join(c.rjust(w) for c, w in zip(columns, widths, strict=True)))
    for row in cells:
        print("  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)))


@contextlib.contextmanager
def stop_between_steps(bars: Bars):
    """The first Ctrl-C stops the study after the step it is in; a second one at once.

    Python raises ``KeyboardInterrupt`` wherever the main thread is, and during a jitted step
    that can be inside a host callback (the iteration counter's taps). A loaded test run once
    hung there for minutes instead of exiting. A flag read between steps keeps the
    exception out of JAX; the step in flight finishes and its record is kept.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return

    def request_stop(signum, frame):
        bars.stop_requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)  # the next one interrupts

    previous = signal.signal(signal.SIGINT, request_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def interrupt_kept(bars: Bars, kept: str):
    """A block in which the first Ctrl-C stops after the step in flight
    (:func:`stop_between_steps`) and the interrupt leaves as one line: ``kept`` says what
    is kept and how to continue."""
    try:
        with stop_between_steps(bars):
            yield
    except (KeyboardInterrupt, RuntimeError) as error:  # JaxRuntimeError is a RuntimeError
        if not is_interrupt(error):
            raise
        bars.close()
        raise Interrupted(f"interrupted; {kept}") from None


def progress(total: int, unit: str):
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, disable=not sys.stderr.isatty(), leave=False)


def percent(value: float, digits: int = 0) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.{digits}f} %"


def percent_range(low: float, high: float) -> str:
    return "-" if math.isnan(low) or math.isnan(high) else f"{100 * low:.0f}-{100 * high:.0f} %"


def as_option(message: str) -> str:
    """``max_mb=-1.0: ...`` -> ``--max-mb -1.0: ...``; lists are shown space-separated."""
    name, _, rest = message.partition("=")
    value, _, explanation = rest.partition(": ")
    value = value.strip("[]").replace(",", "").replace("'", "")
    return f"--{name.replace('_', '-')} {value}: {explanation}"
