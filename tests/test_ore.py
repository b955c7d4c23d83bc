"""Tests of msmill.ore: built-in library, TOML loading, registry, L_ref default flag."""

from __future__ import annotations

import pytest

from msmill import ore as ore_mod
from msmill.errors import MsmillInputError
from msmill.ore import DEFAULT_L_REF_MM, Ore, get_ore, list_ores, register_ore

GOOD = """
name = "TestRock"
description = "unit-test ore"

[breakage]
A_pct = 60.0
b_t_per_kwh = 1.0
l_ref_mm = 25.0
l_ref_source = "calibrated in a test"
source = "test"

[physical]
density_kg_m3 = 2700.0
source = "test"

[elastic]
youngs_modulus_pa = 5.0e10
poisson_ratio = 0.25
source = "test"

[damage]
gamma = 4.0
damage_threshold = 0.9
source = "test"
"""


@pytest.fixture(autouse=True)
def _clean_registry():
    list_ores()  # load the built-ins before taking the snapshot
    before = dict(ore_mod._REGISTRY)
    yield
    ore_mod._REGISTRY.clear()
    ore_mod._REGISTRY.update(before)


def test_builtin_library_matches_paper_table1():
    assert {"UG2", "Platreef"} <= set(list_ores())
    ug2, plat = get_ore("UG2"), get_ore("Platreef")
    assert (ug2.A_pct, ug2.b_t_per_kwh) == (71.8, 1.67)
    assert (plat.A_pct, plat.b_t_per_kwh) == (59.0, 0.5358)
    assert ug2.ab == pytest.approx(119.9, abs=0.1)  # domain notes: A*b = 120


@pytest.mark.parametrize("name", ["ug2", "UG2", " Ug2 ", "PLATREEF"])
def test_lookup_is_case_insensitive(name):
    assert get_ore(name).name.lower() == name.strip().lower()


def test_every_builtin_has_provenance_for_every_parameter_set():
    for name in list_ores():
        o = get_ore(name)
        for key in ("breakage", "l_ref", "physical", "elastic", "tn", "damage"):
            assert o.sources.get(key), (name, key)
        assert o.density_kg_m3 > 1000 and o.youngs_modulus_pa > 1e9
        assert 3.0 <= o.gamma <= 5.4


def test_default_l_ref_is_flagged():
    ug2 = get_ore("UG2")
    assert ug2.l_ref_is_default
    assert ug2.l_ref_mm == DEFAULT_L_REF_MM
    assert "default" in ug2.sources["l_ref"]


def test_default_l_ref_is_geometric_mean_of_jk_fractions():
    # sqrt(63*53)=57.78, sqrt(45*37.5)=41.08, sqrt(31.5*26.5)=28.89, sqrt(22.4*19)=20.63,
    # sqrt(16*13.2)=14.53; geometric mean of these = 29.01 -> 29.0 mm
    assert ore_mod.JK_DROP_WEIGHT_FRACTIONS_MM == (
        (63.0, 53.0), (45.0, 37.5), (31.5, 26.5), (22.4, 19.0), (16.0, 13.2))
    assert DEFAULT_L_REF_MM == 29.0  # by hand as above (arithmetic means would give 32.6)
    assert get_ore("UG2").l_ref_mm == 29.0


def test_from_toml_and_register(tmp_path):
    path = tmp_path / "rock.toml"
    path.write_text(GOOD)
    o = Ore.from_toml(path)
    assert o.l_ref_mm == 25.0 and not o.l_ref_is_default
    assert o.sources["l_ref"] == "calibrated in a test"
    assert o.tn == get_ore("UG2").tn  # default t_n constants
    register_ore(path)
    assert get_ore("testrock").damage_threshold == 0.9
    with pytest.raises(MsmillInputError, match=r"^name"):
        register_ore(path)
    register_ore(o, overwrite=True)


def test_round_trip_to_dict():
    o = get_ore("UG2")
    back = Ore.from_dict(o.to_dict())
    assert back == o


def test_custom_tn_section(tmp_path):
    text = GOOD + '\n[tn]\nt2 = [17.0, 0.52]\nt4 = [4.6, 0.78]\nt25 = [0.34, 1.14]\nt50 = [0.15, 1.26]\nt75 = [0.10, 1.30]\nsource = "table B"\n'
    path = tmp_path / "rock.toml"
    path.write_text(text)
    o = Ore.from_toml(path)
    assert o.tn.k[0] == 17.0 and o.tn.source == "table B"


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("A_pct = 60.0", "A_pct = 160.0", "rock.toml.A_pct"),
        ("b_t_per_kwh = 1.0", "b_t_per_kwh = -1.0", "rock.toml.b_t_per_kwh"),
        ("poisson_ratio = 0.25", "poisson_ratio = 0.7", "rock.toml.poisson_ratio"),
        ("gamma = 4.0", "gamma = 0.01", "rock.toml.gamma"),
        ("damage_threshold = 0.9", "damage_threshold = 1.5", "rock.toml.damage_threshold"),
        ("density_kg_m3 = 2700.0", "density_kg_m3 = 0.0", "rock.toml.density_kg_m3"),
        ('[damage]\ngamma = 4.0\ndamage_threshold = 0.9\nsource = "test"', "[damage]\ngamma = 4.0", "rock.toml.damage.source"),
        ('description = "unit-test ore"', "colour = 3", "rock.toml.colour"),
        ("density_kg_m3 = 2700.0", "density_kg_m3 = 2700.0\nweird = 1", "rock.toml.weird"),
    ],
)
def test_validation_errors_name_the_field(tmp_path, old, new, field):
    path = tmp_path / "rock.toml"
    assert old in GOOD
    path.write_text(GOOD.replace(old, new))
    with pytest.raises(MsmillInputError) as exc:
        Ore.from_toml(path)
    msg = str(exc.value)
    assert msg.startswith(field), msg
    assert "\n" not in msg


def test_bad_files(tmp_path):
    with pytest.raises(MsmillInputError, match=r"^path"):
        Ore.from_toml(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [")
    with pytest.raises(MsmillInputError, match=r"^path"):
        Ore.from_toml(bad)


def test_unknown_ore_suggests():
    with pytest.raises(MsmillInputError, match="did you mean UG2"):
        get_ore("UG3")


def test_with_l_ref():
    o = get_ore("UG2").with_l_ref(22.0, "test calibration")
    assert not o.l_ref_is_default and o.l_ref_mm == 22.0
    with pytest.raises(MsmillInputError, match=r"^l_ref_mm"):
        get_ore("UG2").with_l_ref(-1.0, "x")
