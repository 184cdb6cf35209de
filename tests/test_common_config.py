"""The shared configuration mechanism (bimacppo_common.config): packaged defaults written once,
overlays, strict keys and values, errors that name the file and the key."""
import ast
import dataclasses
import itertools
import pickle
import textwrap

import pytest
import yaml

from bimacppo_common import config
from bimacppo_common.config import (ConfigError, Packaged, config_class, from_dict, invalid, load, runtime,
                                    setting, to_dict)
from conftest import REPO

PACKAGED = """
level: 3
name: base
speeds: [0.0, 2.0]
limit: null
inner:
  gain: 0.5
  flag: true
  table: {left: [1, 2], right: [3, 4]}
"""
_names = itertools.count()


@pytest.fixture
def packaged(tmp_path, monkeypatch):
    """A throwaway package holding one YAML file; returns a function writing it and a Packaged."""
    def make(text=PACKAGED):
        name = f"cfgpkg_{next(_names)}"
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text("")
        (tmp_path / name / "defaults.yaml").write_text(textwrap.dedent(text))
        return Packaged(name, "defaults.yaml")
    monkeypatch.syspath_prepend(str(tmp_path))
    return make


def declare(pk):
    @config_class(pk, "inner")
    class Inner:
        gain: float = setting(lo=0.0, hi=1.0, lo_open=True)
        flag: bool
        table: dict[str, tuple[int, ...]] = setting(keys=("left", "right"), length=2, lo=0)

    @config_class(pk)
    class Outer:
        level: int = setting(lo=0, hi=10)
        name: str = setting(choices=("base", "other"))
        speeds: tuple[float, ...] = setting(lo=0.0, min_length=1)
        limit: float | None = setting(lo=0.0)
        inner: Inner
        origin: str = runtime("")

        def _check(self):
            if self.limit is not None and self.limit < max(self.speeds):
                raise invalid("limit", f"must be >= every speed, got {self.limit}")
    return Outer, Inner


def test_the_packaged_file_is_the_class_default(packaged):
    Outer, Inner = declare(packaged())
    o = Outer()
    assert (o.level, o.name, o.speeds, o.limit) == (3, "base", (0.0, 2.0), None)
    assert o.inner == Inner() and o.inner.table == {"left": (1, 2), "right": (3, 4)}
    assert to_dict(o) == yaml.safe_load(PACKAGED)              # runtime fields are not configuration
    assert Outer(level=5).level == 5 and Outer(level=5).inner == Inner()
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.level = 4
    Outer().inner.table["left"] = (0, 0)                     # defaults are copies, never shared
    assert Outer().inner.table["left"] == (1, 2)


@pytest.mark.parametrize("text, match", [
    (PACKAGED.replace("level: 3\n", ""), r"defaults\.yaml: key 'level' missing from the packaged defaults"),
    (PACKAGED + "extra: 1\n", r"defaults\.yaml: unknown key 'extra' in the packaged defaults"),
    (PACKAGED.replace("gain: 0.5", "gain: 2.0"), r"defaults\.yaml: key 'inner\.gain' must be in \(0\.0, 1\.0\]"),
    (PACKAGED.replace("limit: null", "limit: 1.0"), r"defaults\.yaml: key 'limit' must be >= every speed"),
    ("level: [3\n", r"defaults\.yaml: not valid YAML"),
])
def test_a_broken_packaged_file_fails_at_import_naming_it(packaged, text, match):
    with pytest.raises(ConfigError, match=match):
        declare(packaged(text))


def test_a_default_written_in_the_class_is_refused(packaged):
    pk = packaged("n: 1\n")
    with pytest.raises(TypeError, match="defaults are written in .*defaults.yaml"):
        @config_class(pk)
        class Twice:
            n: int = 1


def test_a_file_overlays_the_defaults_key_by_key(packaged, tmp_path):
    Outer, Inner = declare(packaged())
    f = tmp_path / "variant.yaml"
    f.write_text("# only what changes\ninner:\n  gain: 0.25\n  table: {right: [7, 8]}\nspeeds: [1.0]\n")
    o = load(Outer, f)
    assert o.inner == dataclasses.replace(Inner(), gain=0.25, table={"left": (1, 2), "right": (7, 8)})
    assert o.speeds == (1.0,)                                # a list replaces, it does not merge
    assert (o.level, o.name, o.inner.flag) == (3, "base", True)
    o2 = load(Outer, f, {"inner.flag": False, "inner": {"gain": 1.0}})   # then the overrides, dotted or nested
    assert (o2.inner.flag, o2.inner.gain, o2.inner.table["right"]) == (False, 1.0, (7, 8))
    f.write_text("inner:\n")                                 # an empty section lists nothing
    assert load(Outer, f) == Outer()
    f.write_text("")
    assert load(Outer, f) == Outer()


@pytest.mark.parametrize("data, match", [
    ({"levl": 1}, r"f\.yaml: unknown key 'levl' \(did you mean 'level'\?\)"),
    ({"inner": {"gian": 1}}, r"f\.yaml: unknown key 'inner\.gian' \(did you mean 'gain'\?\)"),
    ({"inner": {"table": {"middle": [1, 1]}}}, r"unknown key 'inner\.table\.middle'"),
    ({"zzz": 1}, r"unknown key 'zzz' \(known: level, name, speeds, limit, inner\)"),
    ({"origin": "x"}, r"unknown key 'origin'"),
    ({"level": True}, r"f\.yaml: key 'level' must be an integer, got True"),
    ({"level": 2.0}, r"key 'level' must be an integer, got 2\.0"),
    ({"level": 11}, r"key 'level' must be in \[0, 10\], got 11"),
    ({"name": "new"}, r"key 'name' must be one of \['base', 'other'\], got 'new'"),
    ({"name": 3}, r"key 'name' must be a string"),
    ({"speeds": [1.0, float("nan")]}, r"key 'speeds' item 1 must be finite"),
    ({"speeds": [-1.0]}, r"key 'speeds' item 0 must be >= 0\.0, got -1\.0"),
    ({"speeds": "fast"}, r"key 'speeds' must be a list"),
    ({"speeds": []}, r"key 'speeds' must list at least 1"),
    ({"inner": {"flag": 1}}, r"key 'inner\.flag' must be true or false, got 1"),
    ({"inner": {"table": {"left": [1]}}}, r"key 'inner\.table\.left' must list 2 values"),
    ({"inner": {"table": {"left": [1, -1]}}}, r"key 'inner\.table\.left' item 1 must be >= 0"),
    ({"inner": 3}, r"key 'inner' is a section and must be a mapping, got int"),
    ({"limit": 1.0}, r"key 'limit' must be >= every speed, got 1\.0"),
])
def test_bad_keys_and_values_name_the_source_and_the_key(packaged, data, match):
    Outer, _ = declare(packaged())
    with pytest.raises(ConfigError, match=match):
        from_dict(Outer, data, "f.yaml")


def test_a_bad_value_is_blamed_on_the_layer_that_set_it(packaged, tmp_path):
    Outer, _ = declare(packaged())
    f = tmp_path / "run.yaml"
    f.write_text("inner:\n  gain: 0.0\n")
    with pytest.raises(ConfigError, match=r"run\.yaml: key 'inner\.gain'") as ei:
        load(Outer, f, {"level": 1})
    assert (ei.value.source, ei.value.key, isinstance(ei.value, ValueError)) == (str(f), ("inner", "gain"), True)
    f.write_text("speeds: [5.0]\n")
    with pytest.raises(ConfigError, match=r"^overrides: key 'limit'"):
        load(Outer, f, {"limit": 1.0})
    with pytest.raises(ConfigError, match=r"^flags: key 'level'"):
        load(Outer, f, {"level": -1}, overrides_source="flags")
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read config file"):
        load(Outer, tmp_path / "nope.yaml")
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match=r"run\.yaml: top level must be a mapping"):
        load(Outer, f)


def test_saved_dicts_round_trip_and_missing_keys_take_the_packaged_defaults(packaged):
    Outer, Inner = declare(packaged())
    o = from_dict(Outer, {"level": 7, "inner": {"gain": 0.1}})
    assert from_dict(Outer, to_dict(o)) == o
    saved = to_dict(o)
    del saved["name"], saved["inner"]["table"]               # saved before these keys existed
    assert from_dict(Outer, saved) == o
    from bimacppo_learning.imitation import ImitationConfig
    from bimacppo_planner.decision import EnvConfig
    for real in (EnvConfig.load(overrides={"action.decision_every": 3}), ImitationConfig.load()):
        assert pickle.loads(pickle.dumps(real)) == real      # configs travel to worker processes
    err = pickle.loads(pickle.dumps(ConfigError("must be odd", source="f.yaml", key="a.b")))
    assert str(err) == "f.yaml: key 'a.b' must be odd" and isinstance(err, ValueError)


def test_a_record_reads_a_missing_key_as_what_its_absence_meant(packaged):
    """A saved record lacks the keys added after it: one that declares ``absent`` takes that
    value (the behaviour before the key), the others the packaged default; a user's overlay
    always takes the packaged default; unknown keys and bad values are refused as in a file."""
    pk = packaged()

    @config_class(pk, "inner")
    class Inner:
        gain: float = setting(lo=0.0, hi=1.0, lo_open=True, absent=0.25)
        flag: bool
        table: dict[str, tuple[int, ...]] = setting(keys=("left", "right"), length=2, lo=0)

    @config_class(pk)
    class Outer:
        level: int = setting(lo=0, hi=10)
        name: str = setting(choices=("base", "other"))
        speeds: tuple[float, ...] = setting(lo=0.0, min_length=1)
        limit: float | None = setting(lo=0.0, absent=9.0)
        inner: Inner

    saved = to_dict(Outer(level=4, limit=5.0))
    assert config.from_record(Outer, saved) == Outer(level=4, limit=5.0)     # a full record reads back
    old = {"level": 4, "name": "base", "speeds": [0.0, 2.0], "inner": {"flag": False, "table": saved["inner"]["table"]}}
    rec = config.from_record(Outer, old, "run.json")
    assert (rec.limit, rec.inner.gain, rec.inner.flag, rec.level) == (9.0, 0.25, False, 4)
    assert config.from_record(Outer, {"level": 2}).inner.gain == 0.25        # a section it predates
    over = from_dict(Outer, old)                                             # an overlay: packaged defaults
    assert (over.limit, over.inner.gain) == (None, 0.5)
    assert config.from_record(Outer, {"limit": 7.0}).limit == 7.0            # a recorded value wins
    assert config.from_record(Outer, {"limit": None}).limit is None
    with pytest.raises(ConfigError, match=r"^run\.json: unknown key 'inner\.gian' \(did you mean 'gain'\?\)"):
        config.from_record(Outer, {"inner": {"gian": 0.3}}, "run.json")
    with pytest.raises(ConfigError, match=r"^run\.json: key 'level' must be in \[0, 10\], got 11"):
        config.from_record(Outer, {"level": 11}, "run.json")
    with pytest.raises(ConfigError, match="expected a mapping"):
        config.from_record(Outer, [1, 2], "run.json")


def test_construction_and_replace_run_the_same_checks(packaged):
    Outer, Inner = declare(packaged())
    with pytest.raises(ConfigError, match=r"^Inner: key 'gain' must be in"):
        Inner(gain=0.0)
    with pytest.raises(ConfigError, match=r"^Outer: key 'limit' must be >= every speed"):
        dataclasses.replace(Outer(), limit=0.5)
    with pytest.raises(ConfigError, match=r"key 'inner' must be a Inner section"):
        Outer(inner={"gain": 0.5})
    o = Outer(speeds=[1, 2], level=4)                        # lists become tuples, ints floats
    assert o.speeds == (1.0, 2.0) and type(o.speeds[0]) is float
    assert dataclasses.replace(o, origin="here").origin == "here"


# ----------------------------------------------------------------------------- the real configs
def _config_classes():
    from bimacppo_curriculum import config as curriculum
    from bimacppo_learning import imitation, ppo_config
    from bimacppo_planner import decision
    for mod in (decision, ppo_config, curriculum, imitation):
        for obj in vars(mod).values():
            if config.is_config_class(obj) and obj.__module__ == mod.__name__:
                yield obj


def test_every_config_class_takes_its_defaults_from_its_packaged_file():
    seen = set()
    for cls in _config_classes():
        spec = cls.__config_spec__
        data = yaml.safe_load(open(spec.packaged.path))
        if spec.section:
            data = data[spec.section]
        assert to_dict(cls()) == data, cls.__name__           # the file lists every key, the class none
        seen.add(cls.__name__)
    assert {"EnvConfig", "ObservationConfig", "PPOConfig", "TrainConfig", "BiMABConfig", "SyntheticConfig",
            "ImitationConfig", "TeacherConfig"} <= seen


def test_one_error_type_for_every_config():
    from bimacppo_curriculum import make_scheduler
    from bimacppo_learning.imitation import ImitationConfig
    from bimacppo_learning.ppo_config import load_config
    from bimacppo_planner.decision import EnvConfig
    with pytest.raises(ConfigError, match=r"unknown key 'observation\.max_svs' \(did you mean 'max_sv'\?\)"):
        EnvConfig.from_dict({"observation": {"max_svs": 2}})
    with pytest.raises(ConfigError, match=r"unknown key 'train\.num_env' \(did you mean 'num_envs'\?\)"):
        load_config(train={"num_env": 2})
    with pytest.raises(ConfigError, match=r"unknown key 'etaa' \(did you mean 'eta'\?\)"):
        make_scheduler("bimab", config={"etaa": 0.1})
    with pytest.raises(ConfigError, match=r"unknown key 'clone\.epoch' \(did you mean 'epochs'\?\)"):
        config.from_dict(ImitationConfig, {"clone": {"epoch": 3}})


def test_an_imitation_file_lists_only_what_it_changes(tmp_path):
    from bimacppo_learning.imitation import ImitationConfig
    f = tmp_path / "short.yaml"
    f.write_text("episodes: 6\nteacher:\n  go:\n    right: [1, 1, 1]\n")
    cfg, base = ImitationConfig.load(f, nvec=(5, 5, 3)), ImitationConfig.load()
    assert (cfg.episodes, cfg.teacher.go["right"], cfg.source) == (6, (1, 1, 1), str(f))
    assert cfg.teacher.go["left"] == base.teacher.go["left"] and cfg.clone == base.clone
    f.write_text("teacher:\n  stop: [0, 5, 1]\n")
    with pytest.raises(ConfigError, match=r"short\.yaml: key 'teacher\.stop' must be \[A1, A2, A3\] within"):
        ImitationConfig.load(f, nvec=(5, 5, 3))


def test_the_common_package_depends_on_no_other_package_of_ours():
    """It sits below every package that uses it: importing any of them from it would be a cycle."""
    ours = {p.name for p in REPO.glob("bimacppo_*") if p.is_dir()}
    offenders = []
    for path in sorted((REPO / "bimacppo_common" / "bimacppo_common").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            offenders += [f"{path.name}: {n}" for n in names if n.split(".")[0] in ours - {"bimacppo_common"}]
    assert offenders == []
