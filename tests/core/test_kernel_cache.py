"""Issue 42, item 1: the quick start broke the install, because numba cached kernels inside the package."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
from support import REPO

from carto_cli.core import kernel_cache

PACKAGE = REPO / "carto_cli"
RUN_A_KERNEL = ("import numpy as np; from carto_cli.sensor.voxel_filter import voxel_filter; "
                "voxel_filter(np.random.default_rng(0).random((50, 2)), 0.1)")


def _cache_files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.suffix in (".nbi", ".nbc")}


def test_the_quick_start_breaks_the_install_no_more(tmp_path):
    """A kernel compiled and cached by a fresh process lands in the per-user cache, not beside its source (where
    a later `pip install -e .` found a package of cache files hiding the editable install)."""
    env = {k: v for k, v in os.environ.items() if k != kernel_cache.ENV}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    before = _cache_files(PACKAGE)
    subprocess.run([sys.executable, "-c", RUN_A_KERNEL], cwd=tmp_path, env=env, check=True, timeout=300)
    assert _cache_files(PACKAGE) == before
    assert _cache_files(tmp_path / "xdg" / "carto" / "numba")


@pytest.mark.skipif(sys.platform in ("win32", "darwin"), reason="the XDG rule is Linux's")
def test_the_cache_follows_the_platform_convention(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert kernel_cache.user_cache_dir() == str(tmp_path / "carto" / "numba")
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/path")  # invalid by the spec: ignored
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert kernel_cache.user_cache_dir() == str(tmp_path / "home" / ".cache" / "carto" / "numba")


def test_numba_cache_dir_set_by_the_user_wins(monkeypatch, tmp_path):
    monkeypatch.setenv(kernel_cache.ENV, str(tmp_path / "mine"))
    assert kernel_cache.decide() == str(tmp_path / "mine")


def test_an_unwritable_home_caches_in_the_temporary_directory(monkeypatch, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    monkeypatch.delenv(kernel_cache.ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))  # carto/numba cannot be made under a file
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(kernel_cache.tempfile, "tempdir", None)  # re-read TMPDIR
    assert kernel_cache.decide().startswith(str(tmp_path / "tmp"))
