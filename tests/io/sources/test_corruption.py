"""Truncated or corrupted recordings give a FormatError naming the file, never another exception."""
import gzip
import shutil

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import SAMPLE_BAG

from carto_cli.core.errors import CartoError
from carto_cli.io.sources.open import open_recording

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def read_all(path):
    """Everything `carto info` touches: topics, static TF, every record."""
    with open_recording(path) as rec:
        rec.topics()
        rec.static_transforms()
        return sum(1 for _ in rec.records())


def check_clean(path):
    try:
        read_all(path)
    except CartoError as e:
        assert str(path) in str(e) or path.name in str(e), str(e)


def damaged_copies(data: bytes, cut: int, flips: list[tuple[int, int]]) -> tuple[bytes, bytes]:
    truncated = data[: cut % len(data)]
    corrupted = bytearray(data)
    for pos, val in flips:
        corrupted[pos % len(data)] = val
    return truncated, bytes(corrupted)


FLIPS = st.lists(st.tuples(st.integers(0, 2**31), st.integers(0, 255)), min_size=1, max_size=8)


@SETTINGS
@given(cut=st.integers(0, 2**31), flips=FLIPS)
def test_ros1_damage(tmp_path, written_recordings, cut, flips):
    _, paths = written_recordings
    data = paths["ros1"].read_bytes()
    for i, blob in enumerate(damaged_copies(data, cut, flips)):
        p = tmp_path / f"damaged{i}.bag"
        p.write_bytes(blob)
        check_clean(p)


@SETTINGS
@given(cut=st.integers(0, 2**31), flips=FLIPS)
def test_standalone_mcap_damage(tmp_path, written_recordings, cut, flips):
    _, paths = written_recordings
    data = paths["mcap"].read_bytes()
    for i, blob in enumerate(damaged_copies(data, cut, flips)):
        p = tmp_path / f"damaged{i}.mcap"
        p.write_bytes(blob)
        check_clean(p)


@SETTINGS
@given(cut=st.integers(0, 2**31), flips=FLIPS, storage=st.sampled_from(["ros2-sqlite3", "ros2-mcap"]))
def test_ros2_storage_damage(tmp_path, written_recordings, cut, flips, storage):
    _, paths = written_recordings
    src = paths[storage]
    for i in range(2):
        dst = tmp_path / f"damaged{i}_{storage}"
        if dst.exists():
            shutil.rmtree(dst)
        shutil.copytree(src, dst)
        (storage_file,) = [f for f in dst.iterdir() if f.suffix in (".db3", ".mcap")]
        blob = damaged_copies(storage_file.read_bytes(), cut, flips)[i]
        storage_file.write_bytes(blob)
        check_clean(dst)


@SETTINGS
@given(cut=st.integers(0, 2**31), flips=FLIPS, gz=st.booleans())
def test_carmen_damage(tmp_path, cut, flips, gz):
    lines = ["# a comment", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for i in range(30):
        t = 10.0 + 0.1 * i
        lines.append(f"ODOM {0.1 * i:.3f} 0 0 0 0 0 {t:.6f} host {t:.6f}")
        ranges = " ".join(f"{1 + (k % 7) * 0.1:.2f}" for k in range(180))
        lines.append(f"FLASER 180 {ranges} {0.1 * i:.3f} 0 0 {0.1 * i:.3f} 0 0 {t:.6f} host {t:.6f}")
    data = ("\n".join(lines) + "\n").encode()
    if gz:
        data = gzip.compress(data)
    for i, blob in enumerate(damaged_copies(data, cut, flips)):
        p = tmp_path / (f"damaged{i}.clf.gz" if gz else f"damaged{i}.clf")
        p.write_bytes(blob)
        check_clean(p)


@settings(max_examples=15, deadline=None)
@given(cut=st.integers(1000, 1_000_000))
def test_real_bag_truncated(tmp_path_factory, cut):
    p = tmp_path_factory.mktemp("cut") / "cut.bag"
    p.write_bytes(SAMPLE_BAG.read_bytes()[:cut])
    check_clean(p)


def test_ros1_field_renamed_by_a_flipped_byte(tmp_path, written_recordings):
    """A byte flipped in a connection header's message definition renames a field (found by test_ros1_damage:
    `intensities` -> `i0tensities`, with the bag header's index position zeroed so the chunks are salvaged): the
    message decodes, then lacks the field; a FormatError naming the file."""
    _, paths = written_recordings
    data = bytearray(paths["ros1"].read_bytes())
    at = data.find(b"intensities")
    assert at >= 0
    data[at + 1] = ord("0")
    data[29] = 0  # in the bag header's index_pos
    p = tmp_path / "renamed.bag"
    p.write_bytes(bytes(data))
    check_clean(p)
