"""JAX's persistent compilation cache in a user cache directory, switched on by the CLI.

A jitted solve or optimiser step compiles in 0.2-8 s, and a new process (every ``prdp-fem``
command, every script run) would compile it again. The ``prdp-fem`` program points JAX's
persistent cache at a directory so that a second process loads the executables instead; a
script asks for the same with :func:`enable_compilation_cache` (importing :mod:`prdp_fem`
changes no JAX setting but float64). The directory:

``PRDP_FEM_COMPILATION_CACHE``
    unset, ``1``, ``on``, ``true`` or ``yes``: ``$XDG_CACHE_HOME/prdp_fem/jax``
    (``~/.cache/prdp_fem/jax``); ``0``, ``off``, ``false`` or ``no``: leave the cache off; any
    other value: that directory.

An explicit ``jax.config.update("jax_compilation_cache_dir", ...)`` made before the import is
left alone. Compilations under 0.2 s are not stored (loading would not pay); the directory is
not capped (JAX's size cap needs one more package): delete it at any time. JAX does not store
executables that contain host callbacks, such as a solve given an
:class:`~prdp_fem.linalg.IterationCounter` (as the inverse driver does, to count iterations inside
line searches): those compile in every process.

>>> from pathlib import Path
>>> cache_directory({"PRDP_FEM_COMPILATION_CACHE": "off"}) is None
True
>>> cache_directory({"XDG_CACHE_HOME": "/tmp/c"}) == Path("/tmp/c/prdp_fem/jax")
True
>>> cache_directory({"PRDP_FEM_COMPILATION_CACHE": "on", "XDG_CACHE_HOME": "/tmp/c"}) == Path(
...     "/tmp/c/prdp_fem/jax")
True
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import jax

__all__ = ["cache_directory", "enable_compilation_cache"]

ENVIRONMENT_VARIABLE = "PRDP_FEM_COMPILATION_CACHE"
_OFF = ("0", "off", "false", "no")
_ON = ("1", "on", "true", "yes")  # the default directory, not a directory named "1"
MIN_COMPILE_SECONDS = 0.2


def cache_directory(environ: Mapping[str, str] = os.environ) -> Path | None:
    """The directory the environment asks for, or ``None`` when the cache is switched off."""
    setting = environ.get(ENVIRONMENT_VARIABLE)
    if setting is not None:
        word = setting.strip().lower()
        if not word or word in _OFF:
            return None
        if word not in _ON:
            return Path(setting).expanduser()
    base = environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "prdp_fem" / "jax"


def enable_compilation_cache(directory: str | os.PathLike | None = None) -> Path | None:
    """Point JAX's persistent compilation cache at ``directory``.

    ``None`` (default): the directory :func:`cache_directory` reads from the environment, or
    no cache at all where ``PRDP_FEM_COMPILATION_CACHE`` switches it off. Returns the
    directory in use (``None``: off). A directory JAX was already given wins (the user chose
    it).
    """
    chosen = jax.config.jax_compilation_cache_dir
    if chosen:
        return Path(chosen)
    if directory is None:
        directory = cache_directory()
    if directory is None:
        return None
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return Path(directory)
