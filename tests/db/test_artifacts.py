import hashlib

import numpy as np
import pytest

from services.storage.artifacts import ArtifactStore, ArtifactWriter


def test_put_bytes_is_content_addressed_and_deduplicated(tmp_path):
    store = ArtifactStore(tmp_path)
    digest = store.put_bytes(b"field")
    assert digest == hashlib.sha256(b"field").hexdigest()
    assert store.put_bytes(b"field") == digest
    assert store.read_bytes(digest) == b"field"
    assert len(list((tmp_path / "sha256").rglob("*"))) == 2  # one fan-out directory, one blob
    assert not list((tmp_path / "incoming").iterdir())


def test_put_file_streams_and_matches_put_bytes(tmp_path):
    source = tmp_path / "cloud.ply"
    source.write_bytes(bytes(range(256)) * 10_000)
    store = ArtifactStore(tmp_path / "store")
    assert store.put_file(source) == hashlib.sha256(source.read_bytes()).hexdigest()


def test_missing_or_malformed_digest_is_a_key_error(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(KeyError, match="not in the store"):
        store.path("0" * 64)
    with pytest.raises(KeyError, match="not a SHA-256"):
        store.path("../etc/passwd")
    assert not store.exists("0" * 64)


def test_failed_write_leaves_no_partial_blob(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(FileNotFoundError):
        store.put_file(tmp_path / "absent")
    assert not list((tmp_path / "incoming").iterdir())
    assert not list((tmp_path / "sha256").iterdir())


def test_a_full_disk_is_storage_full_and_leaves_nothing_behind(small_disk):
    import errno

    from services.storage.artifacts import StorageFull

    store = ArtifactStore(small_disk(1 << 20))
    kept = store.put_bytes(b"kept")
    with pytest.raises(StorageFull) as raised:
        store.put_bytes(np.random.default_rng(0).bytes(2 << 20))
    assert raised.value.errno == errno.ENOSPC and str(store.root) in str(raised.value)
    assert not list((store.root / "incoming").iterdir())
    assert [digest for digest, _ in store.blobs()] == [kept]


def test_the_writer_stores_in_the_background_what_put_bytes_would(tmp_path):
    store = ArtifactStore(tmp_path)
    blobs = {f"part{i}": np.random.default_rng(i).bytes(300_000) for i in range(5)}
    with ArtifactWriter(store) as writer:
        writer.put(dict(list(blobs.items())[:3]))
        writer.put_made(lambda: dict(list(blobs.items())[3:]))
        digests = writer.digests()
    assert digests == {name: hashlib.sha256(content).hexdigest() for name, content in blobs.items()}
    assert all(store.read_bytes(digests[name]) == content for name, content in blobs.items())
    assert not list((tmp_path / "incoming").iterdir())


def test_the_writer_raises_a_full_disk_when_asked_for_the_digests(small_disk):
    from services.storage.artifacts import StorageFull

    store = ArtifactStore(small_disk(1 << 20))
    with ArtifactWriter(store) as writer:
        writer.put({"small": b"kept", "big": np.random.default_rng(0).bytes(2 << 20)})
        with pytest.raises(StorageFull):
            writer.digests()
    assert not list((store.root / "incoming").iterdir())
    assert [digest for digest, _ in store.blobs()] == [hashlib.sha256(b"kept").hexdigest()]
