"""The passport store: checksummed, versioned entries per (vehicle, IMU); one bad unit never stops the others."""

from __future__ import annotations

import functools
import json
import os
import tracemalloc

import pytest

from protocols.passport_codec import write_passport_json
from protocols.passport_entry import passport_checksum
from service.cli import main
from service.demo import demo_passport
from service.passport_store import PassportStore, PassportStoreError


@functools.cache
def passport():
    return demo_passport()[0]


def test_put_then_get_round_trips_and_the_file_is_a_checksummed_entry(tmp_path):
    store = PassportStore(tmp_path)
    path = store.put("uav-1", 2, passport())
    assert path == tmp_path / "uav-1" / "imu2.passport.json"
    entry = json.loads(path.read_text())
    assert entry["type"] == "ins.health.passport-entry" and entry["entry_version"] == 1
    assert entry["sha256"] == passport_checksum(entry["passport"])
    back = store.get("uav-1", 2)
    assert back.to_dict() == passport().to_dict()
    assert store.keys() == [("uav-1", 2)]
    # No temporary file is left next to the entry.
    assert [p.name for p in path.parent.iterdir()] == ["imu2.passport.json"]


def corrupt(path, edit):
    entry = json.loads(path.read_text())
    edit(entry)
    path.write_text(json.dumps(entry))


@pytest.mark.parametrize(
    "damage, reason",
    [
        (
            lambda p: p.write_text('{"type": "ins.health.passport-entry", '),
            "corrupt: not valid JSON",
        ),
        (lambda p: p.write_bytes(b"\xff\xfe\x00garbage"), "corrupt: not valid JSON"),
        (
            lambda p: corrupt(
                p, lambda e: e["passport"]["triads"]["accel"]["nominal"].__setitem__(0, 0.5)
            ),
            "checksum mismatch",
        ),
        (
            lambda p: corrupt(p, lambda e: e.__setitem__("entry_version", 7)),
            "entry version 7 is not supported",
        ),
        (lambda p: corrupt(p, lambda e: e.__setitem__("imu", 5)), "filed under the wrong unit"),
        (
            lambda p: corrupt(p, lambda e: e.__setitem__("type", "ins.health.passport")),
            "a bare passport file",
        ),
    ],
)
def test_a_damaged_entry_is_a_clear_error_for_that_unit_only(tmp_path, damage, reason):
    store = PassportStore(tmp_path)
    store.put("uav-1", 0, passport())
    damage(store.put("uav-2", 0, passport()))
    with pytest.raises(PassportStoreError, match=reason) as info:
        store.get("uav-2", 0)
    assert "uav-2 IMU0" in str(info.value) and str(tmp_path / "uav-2") in str(info.value)
    scan = store.scan()
    assert list(scan.passports) == [("uav-1", 0)] and list(scan.errors) == [("uav-2", 0)]


def test_a_newer_passport_schema_is_reported_with_its_version(tmp_path):
    store = PassportStore(tmp_path)
    path = store.put("uav-1", 0, passport())

    def newer(entry):
        entry["passport"]["schema_version"] = 99
        entry["sha256"] = passport_checksum(entry["passport"])

    corrupt(path, newer)
    with pytest.raises(PassportStoreError, match="schema version 99 is newer"):
        store.get("uav-1", 0)


def test_missing_units_and_bad_keys(tmp_path):
    store = PassportStore(tmp_path)
    with pytest.raises(PassportStoreError, match="missing: no passport file"):
        store.get("uav-9", 1)
    scan = store.scan([("uav-9", 0)])
    assert scan.passports == {} and "missing" in str(scan.errors[("uav-9", 0)])
    with pytest.raises(ValueError, match="not a valid unit key"):
        store.path_for("../etc", 0)
    with pytest.raises(ValueError, match="not a valid unit key"):
        store.path_for("uav-1", 300)


def test_lookups_of_made_up_vehicles_keep_no_memory(tmp_path):
    """A peer inventing a vehicle id per frame: each id is looked up (a vehicle with a passport may
    take an idle one's place) and was remembered as a miss for good, 100 bytes an id (10 MiB for
    100,000 ids in the daemon). Misses are not refusals: the store's memory no longer grows with them."""
    store = PassportStore(tmp_path)

    def miss(first: int, n: int) -> None:
        for k in range(first, first + n):
            with pytest.raises(PassportStoreError):
                store.get(f"made-up-{k}", 0)

    tracemalloc.start()
    miss(0, 20_000)  # past what the interpreter's own caches (interned path parts) settle at
    before = tracemalloc.get_traced_memory()[0]
    miss(20_000, 20_000)
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    assert grown < 100_000, grown  # 20,000 misses remembered took 2.4 MB
    assert store.rejected_counts() == {}


def test_store_command_puts_and_checks(tmp_path, capsys):
    src = tmp_path / "calibrated.json"
    write_passport_json(passport(), src)
    root = tmp_path / "store"
    assert main(["store", "put", str(root), "uav-3", "1", str(src)]) == 0
    assert main(["store", "check", str(root)]) == 0
    out = capsys.readouterr().out
    assert "uav-3 IMU1: ok (demo-uav-imu0, triads accel)" in out
    (root / "uav-3" / "imu1.passport.json").write_text("{}")
    assert main(["store", "check", str(root)]) == 1
    assert "uav-3 IMU1: not a passport-store entry" in capsys.readouterr().out


def _fifo(path):
    os.mkfifo(path)


def _symlink_to_fifo(path):
    os.mkfifo(path.with_name("pipe"))
    path.symlink_to(path.with_name("pipe"))


def _sparse(path):
    with open(path, "wb") as f:
        f.truncate(100 * 2**20)


def _deep(path):
    path.write_text("[" * 100_000 + "]" * 100_000)


@pytest.mark.parametrize(
    "make, problem, reason",
    [
        (_fifo, "not_a_regular_file", r"not a regular file \(a FIFO\)"),
        (_symlink_to_fifo, "not_a_regular_file", r"not a regular file \(a FIFO\)"),
        (lambda p: p.mkdir(), "not_a_regular_file", r"not a regular file \(a directory\)"),
        (_sparse, "too_large", "104857600 bytes exceeds the limit"),
        (_deep, "nested_too_deeply", "nested too deeply"),
    ],
)
def test_an_entry_that_is_not_a_small_regular_file_is_refused_without_reading_it(
    tmp_path, make, problem, reason
):
    """A FIFO (no writer: opening it to read would wait forever), a directory, a 100 MB sparse file and
    JSON nested beyond the parser's recursion limit: each is that unit's refusal, with its reason."""
    store = PassportStore(tmp_path)
    store.put("uav-1", 0, passport())
    path = store.path_for("uav-1", 1)
    make(path)
    with pytest.raises(PassportStoreError, match=reason) as info:
        store.get("uav-1", 1)
    assert info.value.problem == problem
    scan = store.scan()
    assert list(scan.passports) == [("uav-1", 0)] and list(scan.errors) == [("uav-1", 1)]
    assert store.rejected_counts() == {problem: 1}


def test_store_check_names_files_the_daemon_would_not_read(tmp_path, capsys):
    src = tmp_path / "calibrated.json"
    write_passport_json(passport(), src)
    root = tmp_path / "store"
    assert main(["store", "put", str(root), "uav-3", "1", str(src)]) == 0
    good = (root / "uav-3" / "imu1.passport.json").read_bytes()
    (root / "uav-3" / "imu01.passport.json").write_bytes(good)
    (root / "uav-3" / "imu300.passport.json").write_bytes(good)
    (root / "imu0.passport.json").write_bytes(good)
    (root / "uav-3" / ".imu1.passport.json.x.tmp").write_bytes(b"")
    capsys.readouterr()
    assert main(["store", "check", str(root)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "uav-3 IMU1: ok (demo-uav-imu0, triads accel)"
    assert not any("missing" in line for line in lines)
    stray = {line.split(": not read: ")[0]: line.split(": not read: ")[1] for line in lines[1:]}
    assert stray.keys() == {
        str(root / "imu0.passport.json"),
        str(root / "uav-3" / "imu01.passport.json"),
        str(root / "uav-3" / "imu300.passport.json"),
    }
    assert "without leading zeros" in stray[str(root / "uav-3" / "imu01.passport.json")]
    assert "beyond 0..255" in stray[str(root / "uav-3" / "imu300.passport.json")]
    assert "not in a vehicle folder" in stray[str(root / "imu0.passport.json")]
