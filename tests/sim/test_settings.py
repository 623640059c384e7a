"""Settings dataclasses validate on construction and raise InputError; string options are OptionEnums."""

from __future__ import annotations

import pytest

from torchgarment.errors import InputError
from torchgarment.sim.drape import DrapeSettings
from torchgarment.sim.solvers import Preconditioner, Safeguard, SolverKind, SolveSettings


def test_solve_settings_resolve_options_and_validate_on_construction() -> None:
    s = SolveSettings(preconditioner="Scalar", safeguard="project")
    assert s.preconditioner is Preconditioner.SCALAR and s.safeguard is Safeguard.PROJECT
    with pytest.raises(InputError, match=r"unknown preconditioner 'blok'; expected one of: block, scalar"):
        SolveSettings(preconditioner="blok")
    with pytest.raises(InputError, match="chebyshev_rho"):
        SolveSettings(chebyshev_rho=1.0)
    s.validate()  # non-mutating, callable again
    assert s.preconditioner is Preconditioner.SCALAR


def test_drape_settings_resolve_options_and_validate_on_construction() -> None:
    d = DrapeSettings(solver="Newton", sew_solver="gd-chebyshev")
    assert d.solver is SolverKind.NEWTON and d.sew_solver is SolverKind.GD_CHEBYSHEV
    with pytest.raises(InputError, match="edge_length"):
        DrapeSettings(edge_length=-1.0)
    with pytest.raises(InputError, match="expected one of"):
        DrapeSettings(solver="nope")
