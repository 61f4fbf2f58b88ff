"""Configuration values: every one refused by name at configuration time unless the
filter can compute with it, and every file that is not TOML refused in one line."""

from __future__ import annotations

import codecs
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mavest.estimator.config import NUMBER_RANGE, ConfigError, EstimatorConfig, read_toml
from mavest.estimator.layout import make_coefficients
from mavest.service.config import ServiceConfig

FLOAT_KEYS = [f.name for f in dataclasses.fields(EstimatorConfig) if f.type == "float"]
EXTREMES = [1e308, 1e200, NUMBER_RANGE[1], NUMBER_RANGE[0], 1e-200, 5e-324, -1e308]


@pytest.mark.parametrize("key", FLOAT_KEYS)
def test_a_number_is_refused_by_name_or_the_filter_can_compute_with_it(key: str) -> None:
    """Whatever value a key is given, either the configuration refuses it, naming the
    key, or every coefficient the filter derives from it is a finite number."""
    for value in EXTREMES:
        try:
            config = EstimatorConfig(**{key: value})
        except ConfigError as error:
            assert str(error).startswith(key), error
            continue
        record = make_coefficients(config)
        for name in record.dtype.names:
            assert np.all(np.isfinite(record[name])), f"{key} = {value:g}: {name} not finite"


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("gyro_noise_density", 1e308),
        ("initial_tilt_sigma", 1e200),
        ("accel_noise_density", 1e-200),
        ("update_rate", 5e-324),
        ("velocity_time", 1e300),
        ("sigma_beta", float("inf")),
    ],
)
def test_a_value_whose_square_or_reciprocal_overflows_is_refused_in_the_file(
    tmp_path: Path, key: str, value: float
) -> None:
    path = tmp_path / "c.toml"
    path.write_text(f"[estimator]\n{key} = {value!r}\n")
    with pytest.raises(ConfigError, match=f"^{path}: {key}"):
        ServiceConfig.from_toml(path)


@pytest.mark.parametrize(
    ("table", "key"),
    [("input", "settle_time"), ("output", "heartbeat_rate"), ("output", "attitude_rate")],
)
def test_a_service_time_or_rate_must_be_finite(tmp_path: Path, table: str, key: str) -> None:
    """An infinite heartbeat rate would send HEARTBEAT in a loop without pause."""
    path = tmp_path / "c.toml"
    path.write_text(f"[{table}]\n{key} = inf\n")
    with pytest.raises(ConfigError, match=f"{table}.{key} must be ≥ 0, got inf"):
        ServiceConfig.from_toml(path)
    path.write_text(f"[{table}]\n{key} = 2.5\n")
    assert getattr(getattr(ServiceConfig.from_toml(path), table), key) == 2.5


@pytest.mark.parametrize("table", ["input", "output", "signing", "estimator"])
def test_a_section_that_is_not_a_table_is_refused_by_name(tmp_path: Path, table: str) -> None:
    """``output = 5`` for ``[output]`` was a TypeError traceback from the service's tables."""
    path = tmp_path / "c.toml"
    path.write_text(f"{table} = 5\n")
    with pytest.raises(ConfigError, match=rf"\[{table}\] must be a table of settings, got int 5"):
        ServiceConfig.from_toml(path)


def test_a_byte_order_mark_is_read_past_and_utf16_is_named(tmp_path: Path) -> None:
    # what Windows editors save: UTF-8 with a BOM (read as it is), or "Unicode" (UTF-16)
    text = "[estimator]\ngyro_noise_density = 0.004\n"
    path = tmp_path / "c.toml"
    path.write_bytes(codecs.BOM_UTF8 + text.encode())
    assert read_toml(path) == {"estimator": {"gyro_noise_density": 0.004}}
    path.write_text(text, encoding="utf-16")
    with pytest.raises(ConfigError, match=f"^{path} is UTF-16 text: TOML is UTF-8"):
        read_toml(path)


def test_a_file_that_is_not_text_is_not_a_toml_file(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    path.write_bytes(b"\x00\x05\xfd\x09\xfe" * 50)
    with pytest.raises(ConfigError, match=f"^{path} is not a TOML file: byte 2 is not UTF-8"):
        read_toml(path)
