"""Configuration: defaults, presets, YAML round trip, and refusals that name the field."""

from __future__ import annotations

import pytest

from omnitof.slam.config import SlamConfig, load_config, preset_names
from omnitof.errors import ConfigError


def test_presets_exist_and_differ_from_defaults():
    assert {"paper", "laser180", "sim2d"} <= set(preset_names())
    assert load_config(preset="paper").filter.particles == 200
    assert load_config(preset="laser180").filter.particles == 30


def test_yaml_round_trip(tmp_path):
    cfg = load_config(preset="paper", overrides={"filter": {"seed": 42}})
    path = tmp_path / "cfg.yaml"
    path.write_text(cfg.to_yaml())
    assert load_config(path) == cfg


def test_file_overrides_preset_and_keeps_other_fields(tmp_path):
    path = tmp_path / "cfg.yaml"
    path.write_text("filter:\n  particles: 7\nmap:\n  resolution: 0.1\n")
    cfg = load_config(path, preset="paper")
    assert cfg.filter.particles == 7
    assert cfg.map.resolution == 0.1
    assert cfg.filter.resample_threshold == 0.5


@pytest.mark.parametrize(
    "text, field",
    [
        ("filter:\n  particles: 0\n", "filter.particles"),
        ("map:\n  resolution: -0.05\n", "map.resolution"),
        ("motion:\n  alpha3: oops\n", "motion.alpha3"),
        ("filter:\n  partcles: 30\n", "filter.partcles"),
        ("sensor_model:\n  z_hit: 0.5\n", "sensor_model"),
    ],
)
def test_invalid_values_name_the_field(tmp_path, text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert field in str(err.value) and str(path) in str(err.value)


def test_unknown_preset_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="unknown preset 'nope'"):
        load_config(preset="nope")
    path = tmp_path / "bad.yaml"
    path.write_text("filter: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")


def test_defaults_are_documented():
    for section in SlamConfig.model_fields.values():
        for name, field in section.annotation.model_fields.items():
            assert field.description, f"{section.annotation.__name__}.{name} has no description"


@pytest.mark.parametrize("text, got", [("filter: 5\n", "int"), ("filter:\n", "nothing"),
                                       ("map: [0.05]\n", "list")])
def test_a_section_that_is_not_a_mapping_is_refused(tmp_path, text, got):
    # Before, such a section vanished under the defaults without a word.
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=rf"c\.yaml: section \w+: expected a mapping of fields, got {got}"):
        load_config(path, overrides={"filter": {}})


def test_a_file_that_is_not_text_is_refused_with_its_name(tmp_path):
    path = tmp_path / "map.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    with pytest.raises(ConfigError, match=r"map\.png: not a text file"):
        load_config(path)


def test_world_calibration_and_polygon_files_that_are_not_text_are_refused_with_their_name(tmp_path):
    # A PNG given by mistake: one line naming the file, not a UnicodeDecodeError.
    from omnitof.calibration import CalibrationError, load_calibration
    from omnitof.calibration.masks import read_polygon_file
    from omnitof.sim.worlds import WorldError, load_world

    png = tmp_path / "picture.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    with pytest.raises(WorldError, match=r"picture\.png: not a text file"):
        load_world(png)
    with pytest.raises(CalibrationError, match=r"picture\.png: not a text file"):
        load_calibration(png)
    with pytest.raises(CalibrationError, match=r"picture\.png: not a text file"):
        read_polygon_file(png)


def test_dotted_settings_override_like_a_file_and_name_the_field():
    from omnitof.slam.config import parse_setting, settings_overrides
    from omnitof.slam_run import slam_config

    assert parse_setting("backend.enabled=false") == ("backend.enabled", False)
    assert parse_setting("filter.particles=12") == ("filter.particles", 12)
    assert settings_overrides({"filter.particles": 5, "map.resolution": 0.1}) == {
        "filter": {"particles": 5}, "map": {"resolution": 0.1}}
    cfg = slam_config(preset="paper", settings={"filter.particles": 5, "backend.enabled": True}, seed=4)
    assert (cfg.filter.particles, cfg.backend.enabled, cfg.filter.seed) == (5, True, 4)
    # The named options win over a setting of the same field.
    assert slam_config(settings={"filter.particles": 5}, particles=9).filter.particles == 9
    for bad, message in [({"filter": 5}, "expected SECTION.FIELD"), ({"filter.a.b": 5}, "expected SECTION.FIELD"),
                         ({"filter.partcles": 5}, "filter.partcles"), ({"filter.particles": 0}, "filter.particles")]:
        with pytest.raises(ConfigError, match=message):
            slam_config(settings=bad)
    with pytest.raises(ConfigError, match="SECTION.FIELD=VALUE"):
        parse_setting("filter.particles")
