"""Exceptions raised for bad input.

Every user-facing failure caused by input (a malformed file, a broken mesh, a pattern whose panels do not
close) raises a subclass of :class:`TorchGarmentError`. The CLI turns these into one readable line on
stderr and a non-zero exit code.
"""


class TorchGarmentError(Exception):
    """Base class of all errors that torchgarment raises on purpose."""


class InputError(TorchGarmentError, ValueError):
    """Input data (a file, a mesh, a parameter) is malformed or out of range."""


class MeshError(InputError):
    """A mesh is non-manifold, degenerate, empty or otherwise unusable."""


class PatternError(InputError):
    """A sewing pattern is malformed: open panels, self-crossing outlines, bad stitches."""


class NonConvergenceError(TorchGarmentError, RuntimeError):
    """A solve did not reach its tolerance (or met a direction of non-positive curvature)."""


class SingularMatrixError(NonConvergenceError):
    """A sparse factorization failed: the matrix is singular, or its solve returned non-finite values."""


class UnusableResultError(NonConvergenceError):
    """A run ended with a result nobody can use (far from equilibrium, far from the body, exploded): the
    command line exits with code 3 and writes nothing unless told to keep it (``--allow-unconverged``)."""
