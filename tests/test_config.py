"""Configuration: defaults, presets, YAML round trip, and refusals that name the field."""

from __future__ import annotations

import pytest

from omnitof.slam.config import SlamConfig, load_config, parse_setting, preset_names
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
    with pytest.raises(ConfigError, match="not valid YAML") as caught:
        load_config(path)
    # One line, naming the file and the line where the parser gave up (PyYAML's own message
    # spans four and quotes the text).
    assert str(caught.value).startswith(f"{path}:2: ") and "\n" not in str(caught.value)
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


@pytest.mark.parametrize("section, field, value, message", [
    ("map", "resolution", 1e-5, "greater than or equal to 0.001"),  # panicked in the core before
    ("likelihood_field", "z_rand", 0.0, "greater than 0"),  # every particle's weight NaN before
    ("map", "resolution", 1e-4, "greater than or equal to 0.001"),  # aborted allocating 24 GB before
    ("map", "resolution", float("nan"), "finite number"),
    ("map", "max_range", float("inf"), "finite number"),
    ("motion", "alpha1", 1e9, "less than or equal to 10"),
    ("sensor_model", "sigma_hit", 1e-300, "greater than or equal to 0.001"),
    ("filter", "threads", 10**30, "less than or equal to 1024"),  # a TypeError in the core before
    ("sensor_model", "beam_stride", 2**64, "less than or equal to 100000"),
    ("map", "l_occ", 1e300, "less than or equal to 100"),
    ("map", "occupied_threshold", 5.0, r"occupied_threshold 5 must lie in \[l_min, l_max\)"),
    ("scan_matcher", "search_step_xy", 1e-9, "greater than or equal to 0.005"),
    ("backend", "submap_length", 1e-9, "greater than or equal to 0.1"),
])
def test_every_value_is_checked_against_its_real_domain(section, field, value, message):
    with pytest.raises(ConfigError, match=rf"{section}(\.{field})?: .*{message}"):
        load_config(overrides={section: {field: value}})


def test_a_wide_search_of_too_many_poses_is_refused():
    fine = {"search_xy": 5.0, "search_step_xy": 0.01, "search_deg": 180.0, "search_step_deg": 0.1}
    with pytest.raises(ConfigError, match=r"scan_matcher: .*wide search would score 3\.61e\+09 poses per scan"):
        load_config(overrides={"scan_matcher": fine})
    load_config(preset="laser180-scanmatch")  # the preset's search: 13 671 poses


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
    for bad, message in [({"filter": 5}, "expected SECTION.FIELD"), ({"filter.a.b": 5}, "filter.a"), ({"filter..b": 5}, "expected SECTION.FIELD"),
                         ({"scan.multipath": {}, "scan.multipath.enabled": True}, "given twice"),
                         ({"filter.partcles": 5}, "filter.partcles"), ({"filter.particles": 0}, "filter.particles")]:
        with pytest.raises(ConfigError, match=message):
            slam_config(settings=bad)
    with pytest.raises(ConfigError, match="SECTION.FIELD=VALUE"):
        parse_setting("filter.particles")


def test_overrides_in_python_that_are_not_nested_sections_are_refused():
    for bad, message in [("x", "overrides: expected a mapping of sections, .* got str"),
                         ({"filter.particles": 5}, "overrides: 'filter.particles': nest the field"),
                         ({1: 2}, "overrides: section names are strings, got 1")]:
        with pytest.raises(ConfigError, match=message):
            load_config(overrides=bad)
    assert load_config(overrides={"filter": {"particles": 5}}).filter.particles == 5


def test_what_the_project_writes_as_yaml_reads_back_as_written():
    # Strings the loader reads as numbers (1e5 since base 60 went; 10:00 in YAML 1.1) are quoted.
    import yaml

    from omnitof.errors import dump_yaml, load_yaml

    data = {"names": ["1e5", "10:00", "5e-2", "-.5", "010", "0x1F", "2024-01-01", "true", "x"],
            "numbers": [1e5, 0.05, -0.5, 8, float("inf")], "flag": True, "nothing": None}
    text = dump_yaml(data, sort_keys=False)
    assert load_yaml(text) == data and yaml.safe_load(text) == data


def test_numbers_are_read_as_yaml_1_2_reads_them():
    # YAML 1.1 (PyYAML) reads 10:00 as the base-60 integer 600, and 5e-2 as a string.
    from omnitof.slam.config import parse_setting
    from omnitof.slam_run import slam_config

    assert parse_setting("map.resolution=5e-2") == ("map.resolution", 0.05)
    assert parse_setting("filter.particles=10:00") == ("filter.particles", "10:00")
    with pytest.raises(ConfigError, match="filter.particles"):
        slam_config(settings=dict([parse_setting("filter.particles=10:00")]))
    assert [parse_setting(f"a.b={v}")[1] for v in ("-.5", "1_000", "0x1F", ".inf", "3", "true")] == [
        -0.5, 1000, 31, float("inf"), 3, True]


@pytest.mark.parametrize("value, problem", [
    ("9" * 5000, "a value that cannot be read (Exceeds the limit (4300 digits)"),
    ("2024-13-45", "a value that cannot be read (month must be in 1..12)"),
    ("[" * 20000, "nested too deeply to read"),
])
def test_yaml_that_pyyaml_cannot_convert_is_one_line_naming_the_file(tmp_path, value, problem):
    # PyYAML raised ValueError and RecursionError for these: tracebacks before. Worlds,
    # calibrations, polygons, bag sidecars, ROS maps and experiments read YAML the same way.
    from omnitof.sim.worlds import WorldError, load_world

    path = tmp_path / "odd.yaml"
    path.write_text(f"map:\n  resolution: {value}\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: not valid YAML: {problem}"), caught.value
    with pytest.raises(WorldError, match="not valid YAML"):
        load_world(path)
    with pytest.raises(ConfigError, match=r"--set .*the value is not valid YAML"):
        parse_setting(f"map.resolution={value}")


def test_the_core_refuses_a_likelihood_field_without_its_uniform_part():
    # Python's configuration refuses it first; the core, which API users may reach, too.
    import numpy as np

    from omnitof import _core
    from omnitof.slam.driver import core_sections

    sections = core_sections(load_config(preset="laser180-scanmatch"))
    sections["likelihood_field"]["z_rand"] = 0.0
    with pytest.raises(ValueError, match="z_rand above 0"):
        _core.ParticleFilter(**sections, angles=np.linspace(-1.5, 1.5, 181), sensor_pose=np.zeros(3), scan_max_range=20.0)


def test_a_bad_value_is_blamed_on_the_layer_that_set_it(tmp_path):
    # The preset, the file, --set and --particles each blamed for their own value, not the last
    # layer read (a bad --set was reported as the preset's fault).
    from omnitof.slam_run import slam_config

    good = tmp_path / "good.yaml"
    good.write_text("filter:\n  particles: 12\n")
    bad = tmp_path / "bad.yaml"
    bad.write_text("map:\n  resolution: -1\n")
    nulled = tmp_path / "nulled.yaml"
    nulled.write_text("filter:\n  particles:\n")
    cases = [
        (dict(preset="paper", settings={"map.resolution": -1}), "--set map.resolution=-1: invalid configuration: map.resolution"),
        (dict(preset="paper", config=good, settings={"map.resolution": -1}), "--set map.resolution=-1:"),
        (dict(preset="paper", config=bad, settings={"filter.particles": 3}), f"{bad}: invalid configuration: map.resolution"),
        (dict(preset="paper", particles=0), "--particles 0: invalid configuration: filter.particles"),
        (dict(settings={"sensor_model.z_rand": 0.5}), "--set sensor_model.z_rand=0.5: invalid configuration: sensor_model: z_hit"),
        (dict(settings={"filter.seed": int("9" * 300)}), "--set filter.seed=" + "9" * 40 + "...:"),
        # A value set to null is the setter's fault too (it was blamed on the defaults).
        (dict(preset="paper", settings={"filter.particles": None}), "--set filter.particles=null: invalid configuration"),
        (dict(preset="paper", config=nulled), f"{nulled}: invalid configuration: filter.particles"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ConfigError) as err:
            slam_config(**kwargs)
        assert message in str(err.value), (kwargs, str(err.value))
        assert "preset paper" not in str(err.value)


@pytest.mark.parametrize("setting", ["map.resolution", "filter.particles", "motion.alpha1", "scan.height"])
def test_a_boolean_is_no_number(setting):
    # pydantic reads true as 1.0 (or 1): a user who wrote it meant something else.
    from omnitof.slam_run import slam_config

    field = setting.split(".")[1]
    with pytest.raises(ConfigError, match=f"--set {setting}=true: .*{field} expects a number, got the boolean true"):
        slam_config(settings={setting: True})


def test_a_world_with_a_boolean_for_a_number_is_refused(tmp_path):
    from omnitof.errors import InputError
    from omnitof.sim.worlds import load_world

    from omnitof.sim.worlds import worlds_folder

    path = tmp_path / "w.yaml"
    path.write_text((worlds_folder() / "room.yaml").read_text().replace("ceiling_height: 2.6", "ceiling_height: true"))
    with pytest.raises((InputError, ConfigError), match="expects a number, got the boolean true"):
        load_world(path)


def test_a_key_given_twice_is_refused_with_its_line(tmp_path):
    # PyYAML keeps the last value silently: this file would run with 3 particles.
    path = tmp_path / "dup.yaml"
    path.write_text("filter:\n  particles: 30\n  seed: 1\n  particles: 3\n")
    with pytest.raises(ConfigError, match=r"dup\.yaml:4: not valid YAML: the key 'particles' is given twice"):
        load_config(path)
    # A merge key may override on purpose.
    path.write_text("base: &b {particles: 7}\nfilter:\n  <<: *b\n  particles: 8\n")
    from omnitof.errors import load_yaml

    assert load_yaml(path.read_text())["filter"] == {"particles": 8}



@pytest.mark.skipif(not hasattr(__import__("os"), "sched_getaffinity"), reason="CPU affinity is Linux's")
def test_threads_beyond_the_cores_are_the_cores_with_a_warning():
    # 1024 threads on 2 cores made a 3 s run take 47 s; the map does not depend on the count.
    import os
    import warnings

    from omnitof.slam.limits import ThreadsWarning, within_cores

    cores = len(os.sched_getaffinity(0))
    cfg = load_config(preset="paper")
    asked = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"threads": cores + 5})})
    with pytest.warns(ThreadsWarning, match=f"filter.threads {cores + 5} is more than the {cores} cores"):
        assert within_cores(asked).filter.threads == cores
    assert asked.filter.threads == cores + 5  # the configuration asked for stays as it was
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for threads in (0, cores):
            fits = cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"threads": threads})})
            assert within_cores(fits) is fits


def test_the_configuration_text_is_pyyamls_own_for_every_preset():
    # to_yaml uses libyaml's emitter for speed; a resumed `bench` compares this text's digest.
    import yaml

    for name in preset_names():
        cfg = load_config(preset=name)
        assert cfg.to_yaml() == yaml.safe_dump(cfg.model_dump(), sort_keys=False)
        assert SlamConfig.model_validate(yaml.safe_load(cfg.to_yaml())) == cfg


def test_every_preset_reads_under_an_ascii_locale():
    # The presets hold "°" and "×": read as UTF-8 whatever the locale's encoding (LC_ALL=C with
    # UTF-8 mode and locale coercion off makes Python's default ASCII).
    import os
    import subprocess
    import sys

    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    code = ("import locale; from omnitof.slam.config import load_preset, preset_names; "
            "print(locale.getpreferredencoding(False)); [load_preset(n) for n in preset_names()]")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
