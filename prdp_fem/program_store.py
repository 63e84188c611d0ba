"""Executables with the iteration tally's host calls, stored across processes.

JAX's persistent compilation cache (:mod:`prdp_fem.compilation_cache`) refuses every
executable with host callbacks: a callback is a Python object of one process. The iteration
tally's are not of that kind. The program's text names each by its index, and what it does is
one module-level function whose counter and tally arrive as operands (see
:mod:`prdp_fem.executables`). So an inversion step, 2-5 s of XLA compilation that every process
used to pay again, is stored here, and a later process loads it with its own host calls
attached (XLA's ``deserialize_executable(..., host_callbacks=...)``).

The store is the subdirectory ``tally/`` of JAX's persistent cache directory and follows it:
with the cache off (``PRDP_FEM_COMPILATION_CACHE=0``) nothing is stored or loaded. A file's
name is JAX's own cache key of the program (its text, the compile options, the backend, the
JAX and XLA versions), so a program compiled under other settings never loads another's.
Compilations shorter than JAX's minimum for its cache are not stored; files are written
atomically (a temporary file renamed into place); a file that does not load is compiled
again and replaced; the :data:`CAPACITY` most recently used files are kept. A program with
any other host callback (``jax.debug.callback``, pyamg's cycle behind a callable
preconditioner) is compiled as before and never stored.

This reaches into JAX's compiler (``jax._src.compiler.compile_or_get_cached``, replaced
while :func:`compile_lowered` compiles); where this JAX does not offer it, programs compile
as before.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
import zlib
from pathlib import Path

import jax

from .tally import is_tally_host_call

try:  # JAX's compiler entry point and its cache key: internals (see the docstring)
    from jax._src import compilation_cache as _jax_cache
    from jax._src import compiler as _jax_compiler
except ImportError:  # pragma: no cover - depends on the installed JAX
    _jax_cache = _jax_compiler = None

__all__ = ["CAPACITY", "compile_lowered", "store_directory"]

#: The most files kept; the least recently used go first.
CAPACITY = 64
_SUFFIX = ".xla"
#: A file's first bytes: this format, then how many host calls the executable was built with
_MAGIC = b"prdp_fem tally executable 1\n"
_LOCK = threading.Lock()  # one compile through the store at a time (it swaps a JAX global)


def store_directory() -> Path | None:
    """``tally/`` in JAX's persistent cache directory; ``None`` with the cache off or in a
    remote store (a URL such as ``gs://...``: JAX's cache handles those, this one does not)."""
    return _tally_directory(jax.config.jax_compilation_cache_dir,
                            jax.config.jax_enable_compilation_cache)


def _tally_directory(cache_directory: str | None, enabled: bool) -> Path | None:
    if not cache_directory or not enabled or "://" in cache_directory:
        return None
    return Path(cache_directory) / "tally"


def compile_lowered(lowered, compiler_options: dict | None = None):
    """``lowered.compile(compiler_options)``; a program whose only host callbacks are the
    tally's is loaded from the store when it is there and stored once compiled (see the module
    docstring; the options are part of JAX's key)."""
    directory = store_directory()
    if directory is None or not hasattr(_jax_compiler, "compile_or_get_cached") or \
            not hasattr(_jax_cache, "get_cache_key"):
        return lowered.compile(compiler_options=compiler_options)
    with _LOCK:  # read JAX's function under the lock: another compile may have swapped it
        original = _jax_compiler.compile_or_get_cached
        _jax_compiler.compile_or_get_cached = _serving(original, directory,
                                                       threading.get_ident())
        try:
            return lowered.compile(compiler_options=compiler_options)
        finally:
            _jax_compiler.compile_or_get_cached = original


def _serving(original, directory: Path, owner: int):
    """JAX's ``compile_or_get_cached`` serving this thread's tally programs from the store;
    other threads' compilations (they see the swap too) go to JAX's function untouched."""

    def stored_or_compiled(backend, computation, devices, compile_options, host_callbacks,
                           executable_devices, *args, **kwargs):
        def compiled():
            return original(backend, computation, devices, compile_options, host_callbacks,
                            executable_devices, *args, **kwargs)
        if threading.get_ident() != owner or not host_callbacks or \
                not all(map(is_tally_host_call, host_callbacks)):
            return compiled()
        path = _path(directory, computation, devices, compile_options, backend)
        if path is None:
            return compiled()
        loaded = _load(path, backend, executable_devices, compile_options, host_callbacks)
        if loaded is not None:
            return loaded
        start = time.monotonic()
        executable = compiled()
        if time.monotonic() - start >= jax.config.jax_persistent_cache_min_compile_time_secs:
            _store(path, backend, executable, len(host_callbacks))
        return executable

    return stored_or_compiled


def _path(directory: Path, computation, devices, compile_options, backend) -> Path | None:
    try:
        key = _jax_cache.get_cache_key(computation, devices, compile_options, backend)
    except Exception:  # no key, no store: compile as JAX would
        return None
    return directory / f"{key}{_SUFFIX}"


def _load(path: Path, backend, executable_devices, compile_options, host_callbacks):
    """The stored executable with this process's host calls, or ``None`` (absent, or a file
    that does not load: it is compiled again and replaced)."""
    try:
        serialized = _unwrap(path.read_bytes(), len(host_callbacks))
        executable = backend.deserialize_executable(serialized, executable_devices,
                                                    compile_options,
                                                    host_callbacks=host_callbacks)
    except Exception:  # a missing, truncated or foreign file
        return None
    try:
        os.utime(path)  # recently used
    except OSError:
        pass
    return executable


def _store(path: Path, backend, executable, host_calls: int) -> None:
    """Write atomically, then drop the least recently used files beyond :data:`CAPACITY`;
    a store that cannot be written costs the next process a compile, nothing else."""
    try:
        data = _wrap(backend.serialize_executable(executable), host_calls)
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as tmp:
            try:
                tmp.write(data)
            except BaseException:
                os.unlink(tmp.name)
                raise
        os.replace(tmp.name, path)
        stored = sorted(path.parent.glob(f"*{_SUFFIX}"), key=lambda p: p.stat().st_mtime)
        for old in stored[:-CAPACITY]:
            old.unlink(missing_ok=True)
        for left in path.parent.glob("*.tmp"):  # a write a crash cut short, an hour ago
            if time.time() - left.stat().st_mtime > 3600:
                left.unlink(missing_ok=True)
    except Exception:  # full disk, read-only directory, unserialisable
        return


def _wrap(serialized: bytes, host_calls: int) -> bytes:
    """A file's bytes: the header, the executable's count of host calls, the executable."""
    return _MAGIC + host_calls.to_bytes(4, "little") + zlib.compress(serialized)


def _unwrap(data: bytes, host_calls: int) -> bytes:
    """The serialised executable of a file written for ``host_calls`` host calls (a file of
    another format or count raises: loading it with other host calls would be unsafe)."""
    header = _MAGIC + host_calls.to_bytes(4, "little")
    if not data.startswith(header):
        raise ValueError("not a stored executable with this many host calls")
    return zlib.decompress(data[len(header):])
