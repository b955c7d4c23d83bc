"""Solvers are registered objects behind one interface (``msmill.model.solvers``). SYNTHETIC parameters."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msmill.errors import MsmillInputError
from msmill.model import SOLVERS, ExpectedValue, Mill, MonteCarlo, Solver
from msmill.model.solvers import Problem, Solution


def test_the_registry_names_both_solvers_and_each_has_the_interface():
    assert set(SOLVERS) == {"expected_value", "monte_carlo"}
    for name, cls in SOLVERS.items():
        assert cls.name == name
        assert isinstance(cls(), Solver)


def test_a_solver_object_gives_what_its_name_gives(provider, feed, op):
    by_name = Mill("UG2", provider, solver="monte_carlo", parcels_per_step=300, mc_steps=90, seed=3,
                   band_samples=0, envelope=None).run(feed, op, held_below=False)
    by_obj = Mill("UG2", provider, solver=MonteCarlo(300, 90, 3), band_samples=0,
                  envelope=None).run(feed, op, held_below=False)
    assert by_obj.solver == by_name.solver == "monte_carlo"
    np.testing.assert_array_equal(by_obj.product_psd.fractions, by_name.product_psd.fractions)
    assert by_obj.time_to_steady_state_s == by_name.time_to_steady_state_s


def test_mill_uses_the_solver_it_is_given_and_never_asks_its_name(provider, feed, op):
    class HalfFine(ExpectedValue):
        """The expected-value solution with the finest class's product doubled: a solver the Mill cannot know."""

        name = "half_fine"

        def solve(self, problem: Problem) -> Solution:
            sol = super().solve(problem)
            frac = sol.product_fractions.copy()
            frac[0] *= 2.0
            return dataclasses.replace(sol, product_fractions=frac / frac.sum(), notes=("half_fine ran",))

    ev = Mill("UG2", provider, band_samples=0, envelope=None).run(feed, op, timeseries=False, held_below=False)
    own = Mill("UG2", provider, solver=HalfFine(), band_samples=0, envelope=None).run(
        feed, op, timeseries=False, held_below=False)
    assert own.solver == "half_fine" and "half_fine ran" in own.notes
    f0 = ev.product_psd.fractions[0]
    assert own.product_psd.fractions[0] == pytest.approx(2 * f0 / (1 + f0), rel=1e-9)


@pytest.mark.parametrize("spec, allowed", [("montecarlo", "did you mean 'monte_carlo'"),
                                            (42, "Solver interface")])
def test_an_unknown_solver_is_refused_in_one_line(provider, spec, allowed):
    with pytest.raises(MsmillInputError) as err:
        Mill("UG2", provider, solver=spec, envelope=None)
    assert err.value.field == "solver" and allowed in str(err.value)
    assert "\n" not in str(err.value)


def test_monte_carlo_assembles_the_operator_only_when_it_needs_its_march():
    assert MonteCarlo(steps=None).needs_operator()
    assert not MonteCarlo(steps=100).needs_operator()
    assert ExpectedValue().needs_operator()
