"""JAX's persistent compilation cache, for the runner and the benchmarks: a second identical run, and a
``--resume``, load their compiled programs from disk instead of compiling them again.

``configure(directory)`` turns it on (``directory``: ``default_directory()`` when None; ``"none"`` turns it
off) and returns the directory used. Programs that compile in under ``MIN_COMPILE_SECONDS`` are not stored.

Our chunk programs report progress through host callbacks (``jax.debug.callback``, ``jcomps.progress``), and
jax 0.10 never stores a program that has any: its lowered module refers to each callback by an index into the
executable's callback list, and jax's cache reader does not pass the list back when it loads an executable. The
module itself does not depend on the callbacks (the cache key is the same in every process), so this module
lets jax store such programs and, when it loads one, hands it the callbacks of the program being compiled now,
exactly as a fresh compile would get them (``_with_callbacks``). It wraps three private functions of
``jax._src.compiler`` / ``jax._src.compilation_cache`` at the versions pinned in ``pyproject.toml``; if they are
not as expected it leaves jax alone and programs with callbacks are simply compiled every time
(``callbacks_cached()`` says which).
"""

from __future__ import annotations

import contextvars
import functools
import inspect
import os
from typing import Optional

MIN_COMPILE_SECONDS = 1.0
"""Programs that compiled faster than this are not written to the cache (jax's
``jax_persistent_cache_min_compile_time_secs``)."""

OFF = "none"
"""``--compile-cache none``: no persistent cache."""

ENV = "JCOMPS_COMPILE_CACHE"
"""The environment variable that chooses the directory (or ``none``) where no option does."""

_callbacks: contextvars.ContextVar = contextvars.ContextVar("jcomps_host_callbacks", default=None)
_patched: Optional[bool] = None
_hits = [0]
_listening = [False]


def hits() -> int:
    """Programs loaded from the persistent cache in this process so far (since ``configure``)."""
    return _hits[0]


def default_directory() -> str:
    """``$XDG_CACHE_HOME/jcomps/xla`` or ``~/.cache/jcomps/xla``."""
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(home, "jcomps", "xla")


def configure(directory: Optional[str] = None) -> Optional[str]:
    """Turns the persistent compilation cache on in ``directory`` (None: ``default_directory()``), or off with
    ``"none"``; returns the directory, or None when off. Raises ValueError if the directory cannot be created."""
    import jax

    if directory is not None and directory.strip().lower() == OFF:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    directory = os.path.abspath(os.path.expanduser(directory or default_directory()))
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as err:
        raise ValueError(f"invalid compile_cache value {directory!r}: cannot create it ({err.strerror or err}); "
                         f"allowed: a writable directory, or {OFF}") from None
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", directory)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _patch()
    if not _listening[0]:
        from jax._src import monitoring

        def count(event, **kwargs):
            if event == "/jax/compilation_cache/cache_hits":
                _hits[0] += 1

        monitoring.register_event_listener(count)
        _listening[0] = True
    return directory


def from_environment() -> Optional[str]:
    """``configure`` with ``$JCOMPS_COMPILE_CACHE`` (unset: the default directory): what the benchmarks call."""
    return configure(os.environ.get(ENV))


def callbacks_cached() -> bool:
    """Whether programs with host callbacks are cached (the patch applied)."""
    return bool(_patched)


def _patch() -> None:
    """Lets jax write programs with host callbacks to its cache and read them back with the current callbacks."""
    global _patched
    if _patched is not None:
        return
    _patched = False
    try:
        from jax._src import compilation_cache, compiler
    except ImportError:
        return
    compile_or_get_cached = getattr(compiler, "compile_or_get_cached", None)
    cache_write = getattr(compiler, "_cache_write", None)
    get_executable = getattr(compilation_cache, "get_executable_and_time", None)
    expected = {compile_or_get_cached: "host_callbacks", cache_write: "host_callbacks",
                get_executable: "executable_devices"}
    for fn, param in expected.items():
        if fn is None or param not in inspect.signature(fn).parameters:
            return

    @functools.wraps(compile_or_get_cached)
    def compile_or_get_cached_(backend, computation, devices, compile_options, host_callbacks, *args, **kwargs):
        token = _callbacks.set(list(host_callbacks))
        try:
            return compile_or_get_cached(backend, computation, devices, compile_options, host_callbacks, *args,
                                         **kwargs)
        finally:
            _callbacks.reset(token)

    @functools.wraps(cache_write)
    def cache_write_(cache_key, compile_time_secs, module_name, backend, executable, host_callbacks):
        # The executable's callbacks are not part of what is stored (the module names them by index).
        return cache_write(cache_key, compile_time_secs, module_name, backend, executable, [])

    @functools.wraps(get_executable)
    def get_executable_(cache_key, compile_options, backend, executable_devices):
        callbacks = _callbacks.get()
        if not callbacks:
            return get_executable(cache_key, compile_options, backend, executable_devices)
        return _with_callbacks(compilation_cache, cache_key, compile_options, backend, executable_devices,
                               callbacks)

    compiler.compile_or_get_cached = compile_or_get_cached_
    compiler._cache_write = cache_write_
    compilation_cache.get_executable_and_time = get_executable_
    _patched = True


def _with_callbacks(compilation_cache, cache_key, compile_options, backend, executable_devices, callbacks):
    """``compilation_cache.get_executable_and_time``, loading the executable with ``callbacks``."""
    cache = compilation_cache._get_cache(backend)
    if cache is None:
        return None, None
    stored = cache.get(cache_key)
    if stored is None:
        return None, None
    serialized, compile_time = compilation_cache.extract_executable_and_time(
        compilation_cache.decompress_executable(stored))
    executable = backend.deserialize_executable(serialized, executable_devices, compile_options,
                                                host_callbacks=callbacks)
    return executable, compile_time
