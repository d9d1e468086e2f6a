"""``ins-health store put|check``: the daemon's passport store (service/passport_store.py).

* ``put DIR VEHICLE IMU PASSPORT.json [--replace]`` — validate a passport file
  (e.g. from ``ins-health calibrate``) and file it for (vehicle, IMU) as a
  checksummed, versioned entry, written atomically. A unit that already has an
  entry keeps it unless ``--replace`` is given (exit status 2 otherwise).
* ``check DIR`` — load every entry and report each unit as ``ok`` or with the
  reason it is unusable (missing, corrupt, checksum, version, filed under the
  wrong unit), and every file the daemon would not read (a misnamed entry such
  as ``imu01.passport.json``, a file outside a vehicle folder). Exit status 0
  if all are usable, 1 if any is not or a stray file is present, 2 if DIR is
  not a folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli import UsageError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "store", help="file passports into the daemon's passport store, or check it"
    )
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    put = sub.add_parser("put", help="file a passport for (vehicle, IMU)")
    put.add_argument(
        "dir", type=Path, metavar="DIR", help="the passport store ([service] passport_dir)"
    )
    put.add_argument("vehicle", metavar="VEHICLE", help="vehicle id")
    put.add_argument("imu", type=int, metavar="IMU", help="IMU index on the vehicle")
    put.add_argument("passport", type=Path, metavar="PASSPORT.json", help="a passport file")
    put.add_argument(
        "--replace", action="store_true", help="overwrite the unit's entry if it has one"
    )
    put.set_defaults(func=run_put)
    check = sub.add_parser("check", help="load every entry and report the unusable ones")
    check.add_argument("dir", type=Path, metavar="DIR", help="the passport store")
    check.set_defaults(func=run_check)


def run_put(args: argparse.Namespace) -> int:
    from protocols.passport_codec import read_passport_json
    from service.passport_store import PassportStore

    passport = read_passport_json(args.passport)
    store = PassportStore(args.dir)
    existing = store.path_for(args.vehicle, args.imu)
    replaced = existing.exists()
    if replaced and not args.replace:
        raise UsageError(
            f"{args.vehicle} IMU{args.imu} already has an entry ({existing}): give --replace to overwrite it"
        )
    path = store.put(args.vehicle, args.imu, passport)
    note = " (replaced the previous entry)" if replaced else ""
    print(f"{args.vehicle} IMU{args.imu}: {passport.unit_id} filed as {path}{note}")
    return 0


def run_check(args: argparse.Namespace) -> int:
    from service.passport_store import PassportStore

    if not args.dir.is_dir():
        raise UsageError(f"{args.dir}: no such folder (the passport store is a folder)")
    scan = PassportStore(args.dir).scan()
    for (vehicle, imu), passport in sorted(scan.passports.items()):
        print(
            f"{vehicle} IMU{imu}: ok ({passport.unit_id}, triads {', '.join(sorted(t.value for t in passport.triads))})"
        )
    for key, err in sorted(scan.errors.items()):
        print(f"{key[0]} IMU{key[1]}: {err.reason}")
    for path, why in scan.strays:
        print(f"{path}: not read: {why}")
    if not scan.passports and not scan.errors:
        print(f"{args.dir}: no passport entries")
    return 1 if scan.errors or scan.strays else 0
