"""Input validation (one-line MsmillInputError) and the eta_H(e) calibration."""

from __future__ import annotations

import math

import pytest

from msmill.dem import Rotation, Simulation
from msmill.dem.contact import eta_of_restitution, restitution_of_eta
from msmill.errors import MsmillInputError


@pytest.mark.parametrize("e", [0.05, 0.1, 0.2, 0.5, 0.8, 0.95, 0.99])
def test_calibration_inverts_the_clipped_law(e):
    assert restitution_of_eta(eta_of_restitution(e)) == pytest.approx(e, rel=1e-6)


def test_closed_form_damping_overshoots_with_clipping():
    # domain notes: the unclipped closed form gives e = 0.550 for 0.5 and 0.325 for 0.2
    for target, got in ((0.5, 0.550), (0.2, 0.325)):
        ln = math.log(target)
        eta = math.sqrt(5) / 2 * -ln / math.sqrt(math.pi**2 + ln**2)
        assert restitution_of_eta(eta) == pytest.approx(got, abs=2e-3)
        assert eta_of_restitution(target) > eta
    assert eta_of_restitution(1.0) == 0.0


def _sim():
    sim = Simulation((0, 0, 0), (1, 1, 1))
    sim.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.25, density_kg_m3=2700)
    return sim


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda s: Simulation((0, 0, 0), (0, 1, 1)), "domain_max_m"),
        (lambda s: Simulation(periodic=(True, False)), "periodic"),
        (lambda s: s.add_material("x", youngs_modulus_pa=-1, poisson_ratio=0.2,
                                  density_kg_m3=1), "youngs_modulus_pa"),
        (lambda s: s.add_material("x", youngs_modulus_pa=1e9, poisson_ratio=0.6,
                                  density_kg_m3=1), "poisson_ratio"),
        (lambda s: s.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.2,
                                  density_kg_m3=1), "material name"),
        (lambda s: s.set_interaction("rock", "rock", restitution=0.0, friction=0.3),
         "restitution"),
        (lambda s: s.set_interaction("rock", "rock", restitution=0.5, friction=-1),
         "friction"),
        (lambda s: s.set_interaction("rock", "steel", restitution=0.5, friction=0.3),
         "material"),
        (lambda s: s.add_plane((0, 0, 0), (0, 0, 0), material="rock"), "normal"),
        (lambda s: s.add_box((0, 0, 0), (1, -1, 1), material="rock"), "half_extents_m"),
        (lambda s: s.add_box((0, 0, 0), (1, 1, 1), axes=[[1, 1, 0], [0, 1, 0], [0, 0, 1]],
                             material="rock"), "axes"),
        (lambda s: s.add_cylinder((0, 0, 0), (0, 0, 0), 0.1, material="rock"), "p1_m"),
        (lambda s: s.add_cylinder((0, 0, 0), (0, 0, 1), 0.0, material="rock"), "radius_m"),
        (lambda s: s.add_particles([[0, 0]], 0.01, material="rock"), "positions_m"),
        (lambda s: s.add_particles([[0.5, 0.5, 0.5]], -0.01, material="rock"), "radii_m"),
        (lambda s: s.add_source((0, 0, 0), (0.1, 0.1, 0.1), 0.0, radii_m=0.01,
                                material="rock"), "mass_flow_kg_s"),
        (lambda s: s.add_source((0, 0, 0), (0.1, 0.1, 0.1), 1.0, radii_m=0.2,
                                material="rock"), "radii_m"),
        (lambda s: s.add_sink((0, 0, 0), (0, 1, 1)), "region_max_m"),
        (lambda s: s.add_box((0, 0, 0), (1, 1, 1), material="rock", rotation=5.0), "rotation"),
        (lambda s: Rotation((0, 0, 0), (0, 0, 0), 1.0), "axis_dir"),
        (lambda s: s.run(1.0, progress=False), "particles"),
        (lambda s: s.run(-1.0, progress=False), "duration_s"),
        (lambda s: (s.add_particles([[0.5, 0.5, 0.5]], 0.01, material="rock"),
                    s.run(1e-3, dt_s=0.0, progress=False)), "dt_s"),
        (lambda s: (s.add_particles([[0.5, 0.5, 0.5]], 0.3, material="rock"),
                    Simulation(periodic=(True, True, True)).add_material(
                        "rock", youngs_modulus_pa=1e9, poisson_ratio=0.2, density_kg_m3=1),
                    _small_periodic()), "domain_max_m"),
    ],
)
def test_bad_inputs_raise_one_line_errors(call, field):
    with pytest.raises(MsmillInputError) as exc:
        call(_sim())
    assert exc.value.field == field
    assert "\n" not in str(exc.value) and "allowed" in str(exc.value)


def _small_periodic():
    sim = Simulation((0, 0, 0), (0.05, 0.05, 0.05), periodic=(True, True, True))
    sim.add_material("rock", youngs_modulus_pa=1e9, poisson_ratio=0.2, density_kg_m3=1000)
    sim.add_particles([[0.02, 0.02, 0.02]], 0.01, material="rock")
    sim.run(1e-4, progress=False)
