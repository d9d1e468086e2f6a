"""The numpy text DataFlash reader against pymavlink's per-line decoding, its oracle.

:mod:`protocols.dataflash_text_numpy` must give :class:`protocols.logs.LogReader` the same batches
(IMU, order, samples, values bit for bit) and the same counts (``LogStats``) as ``DataFlashStream``
with pymavlink's ``DFMessage``, on every real text log and on logs damaged every way a field log is:
cut anywhere, junk lines, numbers that are not, fields lost, CRLF, types never defined, formats
redefined mid-log. Its number parser must give what Python's ``float`` and ``int`` give.
"""

from __future__ import annotations

import math
import random
from decimal import Decimal

import numpy as np
import pytest
from log_oracle import assert_same_as_pymavlink, current_and_legacy, read_log, three_imus
from pymavlink import DFReader
from real_data import FIELD, LOGS, needs

from protocols.dataflash_text_numpy import _Block, parse_numbers
from protocols.logs import LogReader, write_dataflash_text

REAL_TEXT_LOGS = sorted(LOGS.glob("*.log")) + sorted(FIELD.glob("*.log"))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, bytes]:
    """Three IMUs, in current ArduPilot's ``IMU`` with instance and in the legacy IMU/IMU2/IMU3 names."""
    # a small gyro noise: some values written with an exponent (1e-05)
    folder = tmp_path_factory.mktemp("df")
    return current_and_legacy(folder, write_dataflash_text, "log", 400, gyro_sd=1e-3)


@pytest.mark.parametrize("path", REAL_TEXT_LOGS, ids=lambda p: p.name)
@needs(LOGS)
def test_every_real_text_log_reads_as_pymavlink_reads_it(path, monkeypatch):
    assert_same_as_pymavlink(path, monkeypatch)


@pytest.mark.parametrize("batch", [1, 100, 1000])
@pytest.mark.parametrize("legacy", [False, True])
def test_clean_logs_of_three_imus_in_every_batch_size(tmp_path, clean, monkeypatch, legacy, batch):
    path = tmp_path / "flight.log"
    path.write_bytes(clean[f"legacy{legacy}"])
    assert_same_as_pymavlink(path, monkeypatch, batch_samples=batch)


def test_samples_are_the_fields_pymavlink_text_reader_gives(tmp_path, clean):
    """Against ``DFReader_text`` itself: each IMU line's time, instance, triads and temperature."""
    path = tmp_path / "flight.log"
    path.write_bytes(clean["legacyFalse"])
    reader = DFReader.DFReader_text(str(path))
    want: dict[int, list[list[float]]] = {}
    while (m := reader.recv_match(type=["IMU"])) is not None:
        row = [m.TimeUS * 1e-6, m.AccX, m.AccY, m.AccZ, m.GyrX, m.GyrY, m.GyrZ, m.T]
        want.setdefault(m.I, []).append(row)
    got: dict[int, list[np.ndarray]] = {}
    for b in LogReader(path, batch_samples=64):
        got.setdefault(b.imu, []).append(
            np.column_stack([b.t_s, b.accel_mps2, b.gyro_rps, b.temp_c])
        )
    assert sorted(got) == sorted(want) == [0, 1, 2]
    for imu, rows in want.items():
        np.testing.assert_array_equal(np.concatenate(got[imu]), np.array(rows))


_BAD_NUMBERS = [
    "x", "nan", "inf", "-inf", "1_0", " 1.5", "1.5 ", "+1.5", "1e999", "9" * 400, "", "1.5.5",
    "--1", "0x10", "\u0661\u0662", "1e5", "-0", "-0.0", "1E-3", ".5", "5.", "1e", "e1", "1e+0004",
    "0.000000000000000000000001", "12345678901234567890", "1,5", "\t2",
]  # fmt: skip
"""Field values a damaged or odd log holds: numbers Python reads that the bulk grammar does not,
and text that is no number (the line is a corrupt message)."""


def _damaged(data: bytes, how: str, rng: random.Random) -> bytes:
    """``data`` (a clean text log) damaged one way (a seeded draw of where and what)."""
    if how == "cut":
        return data[: rng.randrange(1, len(data))]
    if how == "crlf":
        return data.replace(b"\n", b"\r\n")
    if how == "comma_delimiter":
        return data.replace(b", ", b",")
    if how == "bit_flips":
        b = bytearray(data)
        for _ in range(20):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        return bytes(b)
    lines = data.decode().split("\n")
    for k in rng.sample(range(3, len(lines) - 1), 25):
        fields = lines[k].split(", ")
        if how == "bad_numbers":
            fields[rng.randrange(1, len(fields))] = rng.choice(_BAD_NUMBERS)
        elif how == "few_fields":
            del fields[rng.randrange(1, len(fields)) :]
        elif how == "junk_lines":
            junk = "IMU, 0.9e-\x00\xe9\r\t"
            fields = ["".join(rng.choice(junk) for _ in range(rng.randrange(40)))]
        elif how == "unknown_types":
            fields[0] = rng.choice(["IMX", "XYZ", "IMU4", "imu", "IMU ", " IMU", "VIBE"])
        elif how == "trailing_space":
            fields[-1] += rng.choice([" ", "\t", " \r", "\r\r"])
        lines[k] = ", ".join(fields)
    return "\n".join(lines).encode()


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize(
    "how",
    [
        "cut", "crlf", "comma_delimiter", "bit_flips", "bad_numbers", "few_fields", "junk_lines",
        "unknown_types", "trailing_space",
    ],
)  # fmt: skip
def test_damaged_logs_read_as_pymavlink_reads_them(tmp_path, clean, monkeypatch, how, seed):
    rng = random.Random(seed)
    path = tmp_path / "flight.log"
    for data in clean.values():
        path.write_bytes(_damaged(data, how, rng))
        assert_same_as_pymavlink(path, monkeypatch, batch_samples=64)


@pytest.mark.parametrize(
    "middle",
    [
        # a second log after the first (its FMT lines again, then its samples: the clock restarts)
        "second_log",
        # IMU redefined with its columns in another order and no temperature
        "reordered",
        # IMU redefined with its instance a float, and with its time a string: read line by line
        "float_instance",
        "text_time",
        # an FMT line that defines nothing usable, then lines of the type it named
        "broken_fmt",
    ],
)
def test_formats_defined_mid_log(tmp_path, clean, monkeypatch, middle):
    data = clean["legacyFalse"]
    lines = data.split(b"\n")
    half = b"\n".join(lines[: len(lines) // 2]) + b"\n"
    row = "IMU, {t}, {i}, 0.5, -0.25, 1e-05, 0.125, 0.0625, -9.75\n"
    fmts = {
        "reordered": "FMT, 129, 36, IMU, QffffffB, TimeUS,AccX,AccY,AccZ,GyrX,GyrY,GyrZ,I\n",
        "float_instance": "FMT, 129, 36, IMU, Qfffffff, TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ\n",
        "text_time": "FMT, 129, 36, IMU, NBffffff, TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ\n",
        "broken_fmt": "FMT, 129, 36, IMU, QBfffffX, TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ\n",
    }
    if middle == "second_log":
        extra = data
    else:
        rows = "".join(row.format(t=9_000_000 + 2500 * k, i=k % 3) for k in range(300))
        extra = (fmts[middle] + rows).encode()
    path = tmp_path / "flight.log"
    path.write_bytes(half + extra + data[len(half) :])
    assert_same_as_pymavlink(path, monkeypatch, batch_samples=50)


@pytest.mark.parametrize("numpy_decoding", [True, False])
def test_an_integer_too_large_for_a_float_is_a_corrupt_message(
    tmp_path, monkeypatch, numpy_decoding
):
    """A time of 400 digits: ``float(int(...))`` overflows. It crashed the reader (OverflowError);
    it is one corrupt message, the lines around it kept."""
    path = tmp_path / "flight.log"
    write_dataflash_text(path, {0: three_imus(40, seed=3)[0]})
    lines = path.read_text().split("\n")
    fields = lines[20].split(", ")
    fields[1] = "9" * 400
    lines[20] = ", ".join(fields)
    path.write_text("\n".join(lines))
    _, stats = read_log(path, numpy_decoding, monkeypatch)
    assert stats.samples == {0: 39} and stats.dropped == {"corrupt_messages": 1}


def _number_strings(rng: random.Random, n: int) -> list[str]:
    """Decimal strings of every shape a log holds, and halfway cases (the exact midpoint of two
    doubles, written with 16 to 19 digits: rounding it twice would go the wrong way)."""
    out = []
    for _ in range(n):
        r = rng.random()
        if r < 0.3:
            out.append(repr(rng.uniform(-20, 20)))
        elif r < 0.45:
            out.append(repr(rng.gauss(0, 1e-3)))
        elif r < 0.5:
            out.append(repr(10 ** rng.uniform(-30, 30)))
        elif r < 0.6:
            out.append(f"{rng.uniform(-1e3, 1e3):.{rng.randint(0, 20)}f}")
        elif r < 0.7:
            out.append(f"{rng.uniform(-1e3, 1e3):.{rng.randint(0, 20)}e}")
        elif r < 0.75:
            out.append(str(rng.randint(-(10**20), 10 ** rng.randint(1, 22))))
        elif r < 0.8:
            out.append("".join(rng.choice("0123456789.-+eE ") for _ in range(rng.randint(0, 8))))
        elif r < 0.85:
            out.append(rng.choice(_BAD_NUMBERS))
        else:
            x = rng.uniform(1, 2) * 2.0 ** rng.randint(-20, 20)
            mid = (Decimal(x) + Decimal(math.nextafter(x, math.inf))) / 2
            out.append(f"{mid:.{rng.randint(15, 18)}e}")
    return out


@pytest.mark.parametrize("integer", [False, True])
def test_numbers_parse_as_python_parses_them(integer):
    """Every field the bulk parser takes (most of them) has Python's value to the bit; what it does
    not take is left to Python (the reader's slow path), never guessed."""
    tokens = _number_strings(random.Random(5), 20_000)
    data = "".join(t + "\n" for t in tokens).encode()
    ends = np.flatnonzero(np.frombuffer(data, np.uint8) == ord("\n"))
    starts = np.concatenate([[0], ends[:-1] + 1])
    pad = 32  # _Block's padding
    value, ok = parse_numbers(_Block.of(data), starts + pad, ends + pad, integer)
    taken = 0
    for token, v, k in zip(tokens, value.tolist(), ok.tolist(), strict=True):
        if not k:
            continue
        taken += 1
        want = float(int(token)) if integer else float(token)
        assert (v, math.copysign(1.0, v)) == (want, math.copysign(1.0, want)), token
    assert taken > (0.015 if integer else 0.8) * len(tokens)
