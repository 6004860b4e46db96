"""Where numba keeps compiled kernels: a per-user cache directory, never the installed package.

Left to itself, numba writes its cache into ``__pycache__`` beside each source file whenever that folder is
writable, which for a ``pip install .`` into a venv means inside ``site-packages/carto_cli``. Those files outlive
an uninstall: ``pip install -e .`` afterwards leaves a ``site-packages/carto_cli`` of cache files only, a
namespace package that hides the editable install (``cannot import name '__version__'``). So the directory is
chosen here, before any kernel is defined; ``NUMBA_CACHE_DIR``, when set, still wins.
"""
from __future__ import annotations

import os
import sys
import tempfile

ENV = "NUMBA_CACHE_DIR"


def user_cache_dir() -> str:
    """The platform's per-user cache folder for carto's kernels (``~/.cache/carto/numba`` on Linux,
    ``$XDG_CACHE_HOME/carto/numba`` when that is set, ``~/Library/Caches/carto/numba`` on macOS,
    ``%LOCALAPPDATA%\\carto\\Cache\\numba`` on Windows)."""
    home = os.path.expanduser("~")
    if sys.platform == "win32":
        return os.path.join(os.environ.get("LOCALAPPDATA") or os.path.join(home, "AppData", "Local"),
                            "carto", "Cache", "numba")
    if sys.platform == "darwin":
        return os.path.join(home, "Library", "Caches", "carto", "numba")
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    # The XDG spec says a relative value is invalid and must be ignored.
    return os.path.join(xdg if os.path.isabs(xdg) else os.path.join(home, ".cache"), "carto", "numba")


def _writable(path: str) -> bool:
    try:
        os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


def decide() -> str:
    """``NUMBA_CACHE_DIR`` when the user set it, else :func:`user_cache_dir`. A home without a writable cache
    folder (a read-only container, a service user) gets a folder in the temporary directory instead: numba
    would otherwise fall back to writing beside the sources."""
    chosen = os.environ.get(ENV, "")
    if chosen:
        return chosen
    chosen = user_cache_dir()
    if _writable(chosen):
        return chosen
    uid = os.getuid() if hasattr(os, "getuid") else os.getpid()
    return os.path.join(tempfile.gettempdir(), f"carto-numba-{uid}")


def choose() -> str:
    """Point numba at :func:`decide`'s folder, for this process and the processes it starts."""
    chosen = decide()
    os.environ[ENV] = chosen
    if "numba.core.config" in sys.modules:
        # numba read its configuration when it was imported (by the caller, before carto): re-read it, or
        # kernels defined from now on would still be cached beside their sources.
        from numba.core import config

        config.reload_config()
    return chosen
