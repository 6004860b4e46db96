"""Write-then-rename, so a failed or interrupted command never leaves a half-written output."""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from carto_cli.core import interrupts
from carto_cli.core.errors import CartoError


@contextmanager
def atomic_output(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; on success it replaces ``path``, on failure it is removed.

    The temporary keeps ``path``'s suffix (or ``suffix``) because some writers (OpenCV) choose the
    encoding by extension.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp creates 0600; outputs should get the usual permissions the umask allows.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        if tmp_path.is_dir():
            shutil.rmtree(tmp_path, ignore_errors=True)
        else:
            tmp_path.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_output(path) as tmp:
        tmp.write_text(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


STAGING_PREFIX = ".carto-partial-"


def existing_outputs(outdir: str | Path, names: Iterable[str]) -> list[str]:
    """Which of ``names`` already exist in ``outdir``."""
    outdir = Path(outdir)
    return [n for n in names if (outdir / n).exists()] if outdir.is_dir() else []


@contextmanager
def output_set(outdir: str | Path, names: Iterable[str]) -> Iterator[Path]:
    """Stage a command's outputs (``names`` in ``outdir``) in a hidden directory inside ``outdir`` and move
    them into place together once every one is written; on failure or interruption none of them moves and the
    earlier set stays as it was. An output of the set that this run did not write (map.carto after
    ``--no-state``) is removed, so the set never mixes two runs. The caller decides beforehand whether an
    existing set may be replaced (``existing_outputs``).

    A staging directory left by a killed process (its pid no longer running) is removed on the next run."""
    outdir = Path(outdir)
    names = list(names)
    created = not outdir.exists()
    outdir.mkdir(parents=True, exist_ok=True)
    _remove_stale_staging(outdir)
    staging = Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=outdir))
    done = False
    try:
        try:
            yield staging
        except OSError as e:
            # A full disk, a quota, a directory made read-only meanwhile: the user's to fix, said in one line
            raise CartoError(f"cannot write the outputs: {e.strerror or e}; the earlier outputs are kept",
                             outdir) from None
        written = {p.name for p in staging.iterdir()}
        with interrupts.deferred():  # a Ctrl-C here would leave a set of two runs' files
            for name in names:
                if name in written:
                    os.replace(staging / name, outdir / name)
                elif (outdir / name).exists():
                    (outdir / name).unlink()
            done = True
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created and not done and not any(outdir.iterdir()):
            outdir.rmdir()


def _remove_stale_staging(outdir: Path) -> None:
    for d in outdir.glob(f"{STAGING_PREFIX}*"):
        pid = d.name[len(STAGING_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not _running(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True
