"""Service configuration: defaults, typed parsing, and clear errors naming the key."""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
from pathlib import Path

import pytest

from estimators.conventions import STANDARD_GRAVITY_MPS2, normal_gravity_mps2
from estimators.nominal_passport import SensorClass
from protocols.mavlink_adapter import MavlinkSettings
from protocols.zenoh_adapter import AckMode, Mode, ZenohSettings
from service.config import ConfigError, MavlinkReader, ServiceConfig, config_from_dict, load_config


def test_empty_document_gives_the_documented_defaults(tmp_path):
    cfg = config_from_dict({}, base_dir=tmp_path)
    assert cfg == ServiceConfig()
    assert cfg.site.local_gravity_mps2 == STANDARD_GRAVITY_MPS2
    assert cfg.zenoh.session.mode is Mode.CLIENT and cfg.zenoh.session.connect == (
        "tcp/127.0.0.1:7447",
    )
    assert cfg.zenoh.frames_key == "ins/*/imu/*" and cfg.zenoh.event_ack is AckMode.RECEIVER
    assert cfg.pipeline.false_alarm_probability == 1e-9 and cfg.pipeline.min_positions == 9
    assert cfg.validity.cross_imu_accel_mps2 == 0.75
    assert cfg.mavlink.reader is MavlinkReader.PROCESS


def test_file_values_types_and_relative_paths(tmp_path):
    path = tmp_path / "svc.toml"
    path.write_text(
        """
[service]
data_dir = "state"
vehicles = ["v1", "v2"]
status_period_s = 2
[site]
latitude_deg = 45.0
[zenoh]
mode = "peer"
connect = []
listen = ["tcp/127.0.0.1:0"]
[mavlink]
enabled = true
device = "udpin:127.0.0.1:0"
signing_key_hex = "%s"
[validity]
stale_run_samples = 50
"""
        % ("ab" * 32)
    )
    cfg = load_config(path)
    assert (
        cfg.service.data_dir == tmp_path / "state"
        and cfg.outbox_path == tmp_path / "state" / "outbox.sqlite"
    )
    assert cfg.service.vehicles == ("v1", "v2") and cfg.service.status_period_s == 2.0
    assert cfg.site.local_gravity_mps2 == pytest.approx(normal_gravity_mps2(45.0))
    assert cfg.zenoh.session.mode is Mode.PEER and cfg.zenoh.session.listen == ("tcp/127.0.0.1:0",)
    assert cfg.zenoh.session.connect == ()
    assert cfg.mavlink.enabled and cfg.mavlink.link.signing_key == bytes.fromhex("ab" * 32)
    assert (
        cfg.mavlink.link.device == "udpin:127.0.0.1:0"
        and cfg.mavlink.link.vehicle == "mavlink.autopilot"
    )
    assert cfg.validity.stale_run_samples == 50


@pytest.mark.parametrize(
    "raw, match",
    [
        ({"servcie": {}}, r"unknown sections \['servcie'\]"),
        ({"service": {"nmae": "x"}}, r"\[service\] has unknown keys \['nmae'\]"),
        ({"service": {"status_period_s": "fast"}}, r"\[service\] status_period_s must be a number"),
        ({"service": {"status_period_s": 0}}, r"status_period_s must be at least 0.01 s"),
        ({"pipeline": {"queue_capacity": True}}, r"queue_capacity must be an integer"),
        ({"pipeline": {"false_alarm_probability": 0.7}}, r"false_alarm_probability must be in"),
        ({"pipeline": {"min_positions": 6}}, r"min_positions must be >= 9"),
        ({"zenoh": {"mode": "server"}}, r"\[zenoh\] zenoh mode must be one of"),
        ({"zenoh": {"connect": "tcp/x:1"}}, r"\[zenoh\] zenoh connect must be a list of endpoints"),
        ({"zenoh": {"conect": []}}, r"\[zenoh\] unknown zenoh setting"),
        ({"zenoh": {"event_ack": "maybe"}}, r"event_ack must be one of"),
        (
            {"mavlink": {"reader": "fork"}},
            r"\[mavlink\] reader must be one of \['process', 'thread'\]",
        ),
        ({"zenoh": {"frames_key": "imu/**"}}, r"frames_key must be under 'ins/'"),
        ({"zenoh": {"enabled": False}}, r"neither \[zenoh\] nor \[mavlink\]"),
        ({"site": {"gravity_mps2": 1.62}}, r"not a value on the Earth"),
        (
            {"mavlink": {"signing_key_hex": "abcd"}},
            r"\[mavlink\] mavlink signing_key_hex must hold 64 hexadecimal digits \(32 bytes\)",
        ),
        (
            {"mavlink": {"signing_key_file": "absent.key"}},
            r"\[mavlink\] mavlink signing_key_file '.*absent.key': No such file",
        ),
        ({"mavlink": {"signing_key_file": 7}}, r"\[mavlink\] signing_key_file must be str"),
        (
            {"mavlink": {"signing_key_file": "k", "signing_key_hex": "ab" * 32}},
            r"\[mavlink\] mavlink signing_key_hex and signing_key_file: give one of them",
        ),
        ({"mavlink": {"source_component": 300}}, r"\[mavlink\] source_component must be in 1..255"),
        # A string here matched no system id: every MAVLink IMU message was silently ignored.
        (
            {"mavlink": {"autopilot_system": "1"}},
            r"\[mavlink\] autopilot_system must be int, got '1'",
        ),
        ({"mavlink": {"baud": 1.5}}, r"\[mavlink\] baud must be int"),
        (
            {"mavlink": {"udp_rcvbuf_bytes": 1024}},
            r"\[mavlink\] udp_rcvbuf_bytes must be in 4096..2147483647, got 1024",
        ),
        ({"mavlink": {"accept_unsigned": 1}}, r"\[mavlink\] accept_unsigned must be bool"),
        (
            {"mavlink": {"raw_scale": {"accel_mps2_per_lsb": -1.0}}},
            r"raw_scale.accel_mps2_per_lsb must be a finite number > 0",
        ),
        (
            {"mavlink": {"imu_index": {"SCALED_IMU2": "1"}}},
            r"imu_index.SCALED_IMU2 must be an integer",
        ),
        (
            {"service": {"status_period_s": float("inf")}},
            r"\[service\] status_period_s must be a finite number",
        ),
        (
            {"service": {"checkpoint_period_s": -30.0}},
            r"\[service\] checkpoint_period_s must be at least 0.01 s",
        ),
        (
            {"service": {"status_period_s": 1e-300}},
            r"\[service\] status_period_s must be at least 0.01 s, got 1e-300",
        ),
        ({"mavlink": {"heartbeat_period_s": 0.0}}, r"heartbeat_period_s must be at least 0.01 s"),
        (
            {"zenoh": {"connect_timeout_s": float("inf")}},
            r"\[zenoh\] connect_timeout_s must be a finite number",
        ),
        (
            {"validity": {"max_rate_hz": float("nan")}},
            r"\[validity\] max_rate_hz must be a finite number",
        ),
        ({"mavlink": {"vehicle": "a/b"}}, r"\[mavlink\] vehicle"),
        ({"mavlink": {"alert_max_per_s": 0}}, r"alert_max_per_s must be > 0"),
        ({"validity": {"timeout_s": -1.0}}, r"\[validity\] timeout_s must be finite and > 0"),
        # Accepted before, then a traceback at start or every delivery failing:
        ({"service": {"data_dir": "~nosuchuser_xyz/data"}}, r"\[service\] data_dir: '~nosuchuser"),
        ({"service": {"data_dir": "a\0b"}}, r"\[service\] data_dir holds a NUL character"),
        (
            {"mavlink": {"enabled": True, "signing_key_file": "~nosuchuser_xyz/key"}},
            r"\[mavlink\] signing_key_file: '~nosuchuser",
        ),
        ({"zenoh": {"ack_timeout_s": 1e300}}, r"\[zenoh\] needs 0 < ack_timeout_s <= 86400"),
        # Bounds from memory or meaning (service.config._UPPER_BOUNDS): each passed before, and
        # 1e12 samples then failed every frame on a 931 GiB allocation, 4e8 took 1.3-1.7 GB.
        (
            {"validity": {"error_window_samples": 10**12}},
            r"^\[validity\] error_window_samples must be at most 600000 \(a minute at 10 kHz",
        ),
        (
            {"validity": {"error_window_samples": 4 * 10**8}},
            r"error_window_samples must be at most",
        ),
        ({"validity": {"cross_imu_accel_mps2": 1e6}}, r"cross_imu_accel_mps2 must be at most 628"),
        ({"validity": {"timeout_s": 1e9}}, r"^\[validity\] timeout_s must be at most 3600"),
        (
            {"validity": {"cross_imu_window_s": 30.0, "cross_imu_persist_windows": 1000}},
            r"cross_imu_window_s x cross_imu_persist_windows must be at most 3600 s",
        ),
        (
            {"pipeline": {"queue_capacity": 10**9}},
            r"^\[pipeline\] queue_capacity must be at most 65536",
        ),
        (
            {"pipeline": {"max_vehicles": 10_000, "max_imus_per_vehicle": 8}},
            r"max_vehicles x max_imus_per_vehicle must be at most 16384",
        ),
        ({"pipeline": {"min_positions": 10**7}}, r"min_positions must be at most 1000"),
        ({"service": {"checkpoint_period_s": 1e9}}, r"checkpoint_period_s must be at most 604800"),
        ({"service": {"outbox_max_mb": 1e12}}, r"outbox_max_mb must be at most 1.759"),
        ({"mavlink": {"alert_max_per_s": 1e6}}, r"alert_max_per_s must be at most 200"),
        ({"zenoh": {"min_acks": 10**6}}, r"min_acks must be at most 256"),
        # The normal-gravity model's ValueError ended the check: no section, no other error said.
        ({"site": {"latitude_deg": 1000.0}}, r"^\[site\] latitude_deg must be at most 90 \(the "),
        ({"site": {"latitude_deg": -90.5}}, r"^\[site\] latitude_deg must be at least -90 \(the "),
        ({"site": {"height_m": -2e4}}, r"^\[site\] height_m must be above -10000 \(below any "),
        (
            {"zenoh": {"connect_timeout_s": 1e300}},
            r"^\[zenoh\] connect_timeout_s must be at most 86400 \(a day, as storage_timeout_s",
        ),
        (
            {"zenoh": {"ack_from": ["gs/1"]}},
            r"^\[zenoh\] ack_from: receiver name 'gs/1' must match",
        ),
        (
            {"zenoh": {"ack_from": ["gs-1", "gs-1"], "min_acks": 2}},
            r"^\[zenoh\] min_acks 2 cannot be met by the 1 receiver\(s\) of ack_from",
        ),
        (
            {"zenoh": {"ack_from": ["gs-1"], "event_ack": "matched"}},
            r'^\[zenoh\] ack_from names receivers: it needs event_ack = "receiver"$',
        ),
        ({"mavlink": {"enabled": True, "messages": []}}, r"\[mavlink\] messages is empty"),
        # pymavlink took it for a UDP address and failed at start ("UDP ports must be specified ...").
        ({"mavlink": {"device": "bogus:://"}}, r"mavlink device 'bogus:://' is no live link"),
        ({"mavlink": {"device": "udpin:0.0.0.0"}}, r"udpin: takes HOST:PORT"),
        # pymavlink would read a log file, or run a regular file under /bin/ as a child process.
        ({"mavlink": {"device": "/usr/bin/env"}}, r"mavlink device '/usr/bin/env' is no live link"),
        ({"mavlink": {"device": "flight.tlog"}}, r"is no live link"),
        ({"mavlink": {"device": "udpin:[::]:14550"}}, r"pymavlink has no IPv6 address"),
        (
            {"service": {"default_grade": "mems"}},
            r"^\[service\] default_grade must be one of \['consumer_mems', 'industrial_mems', "
            r"'tactical', 'navigation', 'none'\], got 'mems'$",
        ),
        ({"service": {"default_grade": False}}, r"\[service\] default_grade must be a string"),
    ],
)
def test_bad_values_are_one_line_errors_naming_the_key(raw, match, tmp_path):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(raw, base_dir=tmp_path)


def test_default_grade_names_the_nominal_class_of_a_unit_without_a_passport(tmp_path):
    """Documented default consumer_mems; "none" is the stated way to turn the nominal passport off."""
    assert ServiceConfig().service.nominal_class is SensorClass.CONSUMER_MEMS
    for cls in SensorClass:
        raw = {"service": {"default_grade": cls.value}}
        assert config_from_dict(raw, base_dir=tmp_path).service.nominal_class is cls
    raw = {"service": {"default_grade": "none"}}
    assert config_from_dict(raw, base_dir=tmp_path).service.nominal_class is None


@pytest.mark.parametrize(
    "device",
    [
        "mcast:",
        "mcast:239.255.145.50:14550",
        "wsserver:0.0.0.0:5760",
        "COM3",
        "/dev/serial/by-id/usb-ArduPilot_fmuv3-if00",
    ],
)
def test_live_links_users_configure_are_accepted(tmp_path, device):
    """Multicast UDP (ArduPilot SITL, MAVProxy), websockets and serial ports pass the device check."""
    assert (
        config_from_dict({"mavlink": {"device": device}}, base_dir=tmp_path).mavlink.link.device
        == device
    )


@pytest.mark.parametrize("name", ["data_dir", "passport_dir"])
def test_a_folder_setting_that_names_a_file_is_a_one_line_error(tmp_path, name):
    """data_dir naming a regular file ended the start in a FileExistsError traceback."""
    (tmp_path / "taken").write_text("not a folder")
    with pytest.raises(ConfigError, match=rf"\[service\] {name} '.*taken' is a file, not a folder"):
        config_from_dict({"service": {name: "taken"}}, base_dir=tmp_path)


def test_every_error_is_reported_on_its_own_line(tmp_path, capsys):
    """Three type mistakes in two sections: three lines from the loader, and from ``ins-health run`` three
    lines on stderr and exit status 2 (an operator fixes them in one pass)."""
    path = tmp_path / "svc.toml"
    path.write_text(
        '[service]\nstatus_period_s = "fast"\ndelivery_retry_s = inf\n'
        '[mavlink]\nautopilot_system = "1"\n'
    )
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert len(info.value.lines) == 3
    assert str(info.value).splitlines() == list(info.value.lines)
    from service.cli import main

    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and all(line.startswith("ins-health run: [") for line in err), err
    assert any("autopilot_system" in line for line in err)
    assert any("delivery_retry_s must be a finite number" in line for line in err)


def test_a_latitude_past_a_pole_and_an_endless_connect_timeout_stop_run_with_status_2(
    tmp_path, capsys
):
    """Before, the latitude ended the check in the normal-gravity model's ValueError (one line
    without its section, the timeout's unsaid) and 1e300 s passed. One line each, exit 2."""
    path = tmp_path / "svc.toml"
    path.write_text("[site]\nlatitude_deg = 1000.0\n[zenoh]\nconnect_timeout_s = 1e300\n")
    from service.cli import main

    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2, err
    assert err[0].startswith("ins-health run: [site] latitude_deg must be at most 90")
    assert err[1].startswith("ins-health run: [zenoh] connect_timeout_s must be at most 86400")


def test_a_configuration_that_is_not_utf8_names_the_file(tmp_path):
    path = tmp_path / "service.toml"
    path.write_bytes('[service]\nname = "sonde-é"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match=r"service.toml: not UTF-8 text"):
        load_config(path)


def test_a_configuration_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Saved by a Windows editor with a UTF-8 byte-order mark: tomllib said "Invalid statement (at line
    1, column 1)". The mark is not text, and the file reads as without it."""
    text = '[service]\nname = "sonde-é"\n'
    path = tmp_path / "service.toml"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    assert load_config(path).service.name == "sonde-é"


def test_invalid_toml_names_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[service\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: not valid TOML"):
        load_config(path)


def test_every_option_is_documented_in_the_example():
    """deploy/ins-health.toml shows every option of every section (the documented defaults)."""
    text = (Path(__file__).parents[1] / "deploy" / "ins-health.toml").read_text()
    shown = tomllib.loads(text)
    # Commented-out options count as shown: strip one leading "# " from each line and parse again.
    uncommented = tomllib.loads(
        "\n".join(
            line[2:] if line.startswith("# ") and "=" in line else line
            for line in text.splitlines()
        )
    )
    cfg = ServiceConfig()
    for section in dataclasses.fields(cfg):
        names = {f.name for f in dataclasses.fields(getattr(cfg, section.name))}
        if section.name == "zenoh":
            names = (names - {"session"}) | set(ZenohSettings._KEYS)
        if section.name == "mavlink":
            names = (names - {"link"}) | set(MavlinkSettings._KEYS)
        assert names <= set(uncommented.get(section.name, {})), (
            section.name,
            names - set(uncommented.get(section.name, {})),
        )
    assert set(shown) == {f.name for f in dataclasses.fields(cfg)}


def test_signing_key_file_is_read_relative_to_the_configuration_and_checked(tmp_path):
    """The key file holds 64 hex digits (surrounding white space allowed); a short key, a non-hex one
    and a FIFO (which a blocking open would wait on forever) are one-line errors."""
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "mav.key").write_text("ab" * 32 + "\n")
    cfg = config_from_dict({"mavlink": {"signing_key_file": "keys/mav.key"}}, base_dir=tmp_path)
    assert cfg.mavlink.link.signing_key == bytes.fromhex("ab" * 32)
    assert not cfg.mavlink.link.accept_unsigned
    (tmp_path / "short.key").write_text("ab" * 16)
    (tmp_path / "words.key").write_text("not a key")
    os.mkfifo(tmp_path / "fifo.key")
    for name, match in (
        ("short.key", "must hold 64 hexadecimal digits"),
        ("words.key", "must hold 64 hexadecimal digits"),
        ("fifo.key", "is not a regular file"),
    ):
        with pytest.raises(ConfigError, match=rf"\[mavlink\] mavlink signing_key_file.*{match}"):
            config_from_dict({"mavlink": {"signing_key_file": name}}, base_dir=tmp_path)


@pytest.mark.parametrize(
    ("key", "value", "said"),
    [
        ("storage_timeout_s", 0.5, "storage_timeout_s must be in [1, 86400] s"),
        ("storage_timeout_s", 1e9, "storage_timeout_s must be in [1, 86400] s"),
        ("max_held_events", 0, "max_held_events must be an integer in [1, 1000000]"),
        ("max_held_events", 10**12, "max_held_events must be an integer in [1, 1000000]"),
        ("outbox_max_pending", 10**9, "outbox_max_pending must be an integer in [1, 10000000]"),
    ],
)
def test_the_delivery_and_storage_bounds_are_checked_at_start(key, value, said):
    """Issue 29's keys: memory held while storage is away, a sink's backlog, and how long storage may
    be away before the daemon exits for systemd to restart it, each bounded."""
    with pytest.raises(ConfigError, match=re.escape(said)):
        config_from_dict({"service": {key: value}})
    assert getattr(config_from_dict({"service": {}}).service, key) > 0
