"""Scenes declare which physical effects a simulation has; :meth:`Scene.build` composes only those terms.

A :class:`Scene` holds the garment, the optional body (as a signed distance field and/or a triangle mesh),
optional pins, the :class:`Material` and the set of :class:`Effect` s. With ``effects=None`` the effects are
detected from what the scene holds:

* ``STRETCH`` when the garment has 2D rest positions ``p``; ``SEW`` when it has seam pairs;
* ``BEND`` and ``GRAVITY`` always;
* ``PINS`` when pin indices are given; ``BODY_BARRIER`` when a body SDF is given;
* never ``SELF_CONTACT``, ``BODY_CONTACT`` nor ``PANEL_CONTACT`` (the IPC terms are slower; ask for them).

An effect asked for explicitly without what it needs (``SEW`` without seam pairs, ``BODY_BARRIER`` without an
SDF, ...) raises :class:`~torchgarment.errors.InputError`.

:meth:`Scene.build` also rejects, up front and with a one-line message, input the solvers cannot handle
stably (:func:`check_scene_input`): non-finite coordinates, face indices out of range, a garment or body that
is not in metres (a garment spanning more than :data:`MAX_EXTENT` metres, or much larger than the body: given
in millimetres?), rest edges of (near-)zero length (shorter than :data:`MIN_REST_EDGE_RATIO` times the
median) and sliver or degenerate rest triangles (smallest angle below :data:`MIN_REST_ANGLE_DEG`). The
thresholds sit far from real garments (meshed patterns have edges above 0.5x the median and angles above
25 degrees; GarmentCode's jumpsuit at 1 cm: 0.09x and 5 degrees) and far below the cases that break the
solvers (a 0.003 degree sliver makes both GD and Newton stall; a 1e-6 x edge makes its spring 1e6 x stiffer).

:meth:`Scene.build` returns a :class:`SimModel`: a frozen composition (warp.sim style) of the requested
:class:`~torchgarment.sim.energies.base.EnergyTerm` s with the interface the solvers use (total energy,
analytic gradient, Hessian diagonal and blocks, barrier step bounds and feasibility projection).

Example::

    scene = Scene(garment=mesh, body_sdf=BodySDF.from_body(body))
    model = scene.build()            # stretch, sew, bend, gravity, body_barrier
    E, g = model.value_and_grad(mesh.x)
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from types import ModuleType

import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.options import OptionEnum
from torchgarment.sim.energies.barrier import DEFAULT_BARRIER_DHAT, DEFAULT_BARRIER_MU, BodyBarrier
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.bend import DEFAULT_BEND_STIFFNESS, QuadraticBending
from torchgarment.sim.energies.gravity import DEFAULT_DENSITY, STANDARD_GRAVITY, Gravity
from torchgarment.sim.energies.pins import DEFAULT_PIN_STIFFNESS, Pins
from torchgarment.sim.energies.sew import DEFAULT_SEW_STIFFNESS, SewingSprings
from torchgarment.sim.energies.stretch import DEFAULT_STRETCH_STIFFNESS, PlanarSprings, check_positions
from torchgarment.structures.garment_mesh import GarmentMesh

MAX_EXTENT = 10.0
"""Largest bounding-box side, in metres, of a garment (3D positions or 2D pattern) or body a scene accepts."""

MAX_GARMENT_TO_BODY = 10.0
"""Largest ratio of the garment's bounding-box side to the body's (SDF box) a scene accepts."""

MIN_REST_EDGE_RATIO = 1e-3
"""Shortest rest edge a scene accepts, as a fraction of the median rest edge (its spring would be 1000x
stiffer)."""

MIN_REST_ANGLE_DEG = 0.1
"""Smallest rest-triangle angle in degrees a scene accepts (bending weights grow like 1 / angle)."""


class Effect(OptionEnum):
    """Physical effects a scene may include (each becomes one energy term)."""

    STRETCH = "stretch"
    """In-panel springs with rest lengths from the pattern (:class:`PlanarSprings`)."""
    SEW = "sew"
    """Zero-rest-length springs on the seam pairs (:class:`SewingSprings`)."""
    BEND = "bend"
    """Quadratic bending, also across seams (:class:`QuadraticBending`)."""
    GRAVITY = "gravity"
    """Weight of the cloth (:class:`Gravity`)."""
    PINS = "pins"
    """Sticking springs to targets: pins and belts (:class:`Pins`)."""
    BODY_BARRIER = "body_barrier"
    """Log barrier on the body SDF (:class:`BodyBarrier`, Wang et al. 2018)."""
    SELF_CONTACT = "self_contact"
    """IPC cloth-cloth contact (``torchgarment.sim.contact.SelfContact``)."""
    BODY_CONTACT = "body_contact"
    """IPC contact against the body triangle mesh (``torchgarment.sim.contact.BodyMeshContact``)."""
    PANEL_CONTACT = "panel_contact"
    """IPC contact within each panel, panels free to cross each other
    (``torchgarment.sim.contact.SelfContact`` with ``vertex_panel_ids``; the sewing stage's self-contact,
    term ``"panel_contact"``)."""


@dataclass
class Material:
    """Cloth and interaction parameters, SI units.

    Attributes:
        stretch_stiffness: ``Y`` of the planar springs in N (about 2,900 N/m membrane stiffness at 1 cm
            edges).
        sew_stiffness: seam spring constant in N/m.
        bend_stiffness: bending stiffness in N m (J).
        density: areal density in kg/m^2.
        gravity: gravitational acceleration in m/s^2 (along -Y).
        barrier_mu: weight of the body log barrier in J (Wang 2018: 0.01).
        barrier_dhat: range of the body barrier in m (the IPC-form range-limited log barrier, see
            :mod:`torchgarment.sim.energies.barrier`), or None for the paper's unbounded ``-mu log phi``.
        barrier_offset: clearance in m restored by ``project_feasible``; None = ``max(1 mm, voxel / 4)``.
        pin_stiffness: pin spring constant in N/m.
        contact_dhat: IPC activation distance in m.
        contact_stiffness: IPC barrier stiffness in Pa; None = IPC's adaptive minimum.
    """

    stretch_stiffness: float = DEFAULT_STRETCH_STIFFNESS
    sew_stiffness: float = DEFAULT_SEW_STIFFNESS
    bend_stiffness: float = DEFAULT_BEND_STIFFNESS
    density: float = DEFAULT_DENSITY
    gravity: float = STANDARD_GRAVITY
    barrier_mu: float = DEFAULT_BARRIER_MU
    barrier_dhat: float | None = DEFAULT_BARRIER_DHAT
    barrier_offset: float | None = None
    pin_stiffness: float = DEFAULT_PIN_STIFFNESS
    contact_dhat: float = 2.0e-3
    contact_stiffness: float | None = None


@dataclass
class Scene:
    """What to simulate.

    Attributes:
        garment: the garment mesh; its ``x`` is the initial state and its ``p`` the rest pattern.
        body_sdf: signed distance field of the body (a :class:`~torchgarment.sdf.BodySDF`), or None.
        body_vertices: (B, 3) body mesh positions in metres (for ``BODY_CONTACT``), or None.
        body_faces: (G, 3) long body triangles, or None.
        pin_indices: (P,) long pinned garment vertices, or None.
        pin_targets: (P, 3) their targets in metres; None = their positions in ``garment.x``.
        effects: the effects to build, or None to detect them (see the module docstring).
        material: parameters.
    """

    garment: GarmentMesh
    body_sdf: torch.nn.Module | None = None
    body_vertices: torch.Tensor | None = None
    body_faces: torch.Tensor | None = None
    pin_indices: torch.Tensor | None = None
    pin_targets: torch.Tensor | None = None
    effects: set[Effect] | None = None
    material: Material = field(default_factory=Material)

    def detected_effects(self) -> set[Effect]:
        """The effects ``effects=None`` stands for."""
        out = {Effect.BEND, Effect.GRAVITY}
        if self.garment.p is not None:
            out.add(Effect.STRETCH)
        if self.garment.seam_pairs.shape[0] > 0:
            out.add(Effect.SEW)
        if self.pin_indices is not None:
            out.add(Effect.PINS)
        if self.body_sdf is not None:
            out.add(Effect.BODY_BARRIER)
        return out

    def resolved_effects(self) -> list[Effect]:
        """The effects to build, in :class:`Effect` order, checked against what the scene holds.

        Raises:
            InputError: an unknown effect name, or an effect asked for without what it needs.
        """
        if not isinstance(self.garment, GarmentMesh):
            raise InputError(f"Scene.garment must be a GarmentMesh, got {type(self.garment).__name__}")
        wanted = self.detected_effects() if self.effects is None else _as_effects(self.effects)
        g = self.garment
        missing = {
            Effect.STRETCH: (g.p is None, "the garment has no 2D rest positions p"),
            Effect.SEW: (g.seam_pairs.shape[0] == 0, "the garment has no seam pairs"),
            Effect.PINS: (self.pin_indices is None, "no pin_indices were given"),
            Effect.BODY_BARRIER: (self.body_sdf is None, "no body_sdf was given"),
            Effect.BODY_CONTACT: (self.body_vertices is None or self.body_faces is None,
                                  "body_vertices and body_faces were not given"),
            Effect.PANEL_CONTACT: (g.panel_ids is None, "the garment has no panel_ids"),
        }
        for eff in wanted:
            bad, why = missing.get(eff, (False, ""))
            if bad:
                raise InputError(f"effect {eff.value!r} was asked for but {why}")
        return [e for e in Effect if e in wanted]

    def build(self) -> "SimModel":
        """Build the :class:`SimModel` with exactly the resolved effects' terms.

        Raises:
            InputError: see :meth:`resolved_effects`; bad pins; an SDF on another device; missing contact
                module; non-finite coordinates; a garment or body not in metres (see
                :func:`check_scene_input`).
            MeshError: faces out of range; (near-)zero rest edges or sliver rest triangles.
        """
        effects = self.resolved_effects()
        check_scene_input(self.garment, self.body_sdf,
                          check_rest=Effect.STRETCH in effects or Effect.BEND in effects)
        g, m = self.garment, self.material
        V = g.num_vertices
        terms: list[EnergyTerm] = []
        for eff in effects:
            if eff is Effect.STRETCH:
                terms.append(PlanarSprings.from_mesh(g, stiffness=m.stretch_stiffness))
            elif eff is Effect.SEW:
                terms.append(SewingSprings.from_mesh(g, stiffness=m.sew_stiffness))
            elif eff is Effect.BEND:
                terms.append(QuadraticBending.from_mesh(g, stiffness=m.bend_stiffness))
            elif eff is Effect.GRAVITY:
                terms.append(Gravity.from_mesh(g, density=m.density, gravity=m.gravity))
            elif eff is Effect.PINS:
                terms.append(self._pins())
            elif eff is Effect.BODY_BARRIER:
                sdf = self.body_sdf
                dev = getattr(sdf, "device", g.device)
                if torch.device(dev) != g.device:
                    raise InputError(f"the body SDF is on {dev} but the garment is on {g.device}")
                terms.append(BodyBarrier(sdf, V, mu=m.barrier_mu, dhat=m.barrier_dhat,
                                         offset=m.barrier_offset))
            elif eff is Effect.SELF_CONTACT:
                contact = _contact_module(eff)
                terms.append(contact.SelfContact(
                    g.faces, _rest_positions(g), m.contact_dhat, m.contact_stiffness, V,
                    seam_pairs=g.seam_pairs, areal_density=m.density))
            elif eff is Effect.BODY_CONTACT:
                contact = _contact_module(eff)
                terms.append(contact.BodyMeshContact(
                    g.faces, self.body_vertices, self.body_faces, m.contact_dhat, m.contact_stiffness,
                    garment_rest_positions=_rest_positions(g), self_contact=False, seam_pairs=g.seam_pairs,
                    areal_density=m.density))
            elif eff is Effect.PANEL_CONTACT:
                contact = _contact_module(eff)
                terms.append(contact.SelfContact(
                    g.faces, _rest_positions(g), m.contact_dhat, m.contact_stiffness, V,
                    vertex_panel_ids=g.vertex_panel_ids, areal_density=m.density,
                    step_bound=contact.StepBound.ADDITIVE))
        return SimModel(terms, V, device=g.device, dtype=g.dtype, effects=effects)

    def _pins(self) -> Pins:
        g = self.garment
        idx = self.pin_indices
        if not isinstance(idx, torch.Tensor):
            try:
                idx = torch.as_tensor(idx, dtype=torch.long, device=g.device)
            except (TypeError, ValueError, RuntimeError) as exc:
                raise InputError(f"pin_indices cannot be converted to a long tensor: {exc}") from exc
        idx = idx.to(g.device).reshape(-1)
        if idx.dtype != torch.long:
            raise InputError(f"pin_indices must be integers, got {idx.dtype}")
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= g.num_vertices):
            raise InputError(f"pin_indices outside [0, {g.num_vertices})")
        tgt = g.x.detach()[idx] if self.pin_targets is None else torch.as_tensor(
            self.pin_targets, dtype=g.dtype, device=g.device)
        return Pins(idx, tgt, g.num_vertices, stiffness=self.material.pin_stiffness)


class SimModel(torch.nn.Module):
    """A frozen composition of energy terms: the object solvers work on.

    Built by :meth:`Scene.build`; treat it as immutable (build a new one to change effects).

    Attributes:
        terms: ``nn.ModuleList`` of the terms, in :class:`Effect` order.
        effects: the effects built, one per term.
        num_vertices: V. device, dtype: of the garment.
    """

    def __init__(self, terms: Sequence[EnergyTerm], num_vertices: int, *, device: torch.device,
                 dtype: torch.dtype, effects: Sequence[Effect] = ()) -> None:
        super().__init__()
        names = [t.name for t in terms]
        if len(set(names)) != len(names):
            raise InputError(f"duplicate energy term names: {names}")
        self.terms = torch.nn.ModuleList(terms)
        self.effects = tuple(effects)
        self.num_vertices = int(num_vertices)
        self.device = torch.device(device)
        self.dtype = dtype
        self._const_diag: tuple | None = None  # (key, (V, 3, 3)) cache of constant_hessian_diagonal
        # (V, 3, 3) last full diagonal of the non-volatile terms
        self._elastic_diag: torch.Tensor | None = None
        #: rows (long) whose diagonal the volatile terms (barrier, contact) set in the last
        #: :meth:`value_grad_hessian_diagonal`; None = possibly all
        self.last_volatile_rows: torch.Tensor | None = None

    def reset_caches(self) -> None:
        """Forget the state earlier evaluations left (each term's :meth:`EnergyTerm.reset_cache` and the
        cached elastic diagonal), so that a solve from the same start repeats an earlier one bit for bit."""
        for t in self.terms:
            t.reset_cache()
        self._elastic_diag = None
        self.last_volatile_rows = None

    @property
    def term_names(self) -> tuple[str, ...]:
        """Names of the terms, in order."""
        return tuple(t.name for t in self.terms)

    def term(self, name: str) -> EnergyTerm:
        """The term called ``name``.

        Raises:
            InputError: no such term in this model.
        """
        for t in self.terms:
            if t.name == name:
                return t
        raise InputError(f"this model has no term {name!r}; it has {list(self.term_names)}")

    # ------------------------------------------------------------------ energy and derivatives
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Total energy in joules, autograd-differentiable (same as :meth:`energy`)."""
        return self.energy(x)

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """Total energy () in joules of positions ``x`` (V, 3); differentiable in ``x`` and term
        parameters."""
        check_positions(x, self.num_vertices, "SimModel")
        total = torch.zeros((), dtype=x.dtype, device=x.device)
        for t in self.terms:
            total = total + t(x)
        return total

    def value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Total energy () and its analytic gradient (V, 3) (sum of the terms' analytic results)."""
        check_positions(x, self.num_vertices, "SimModel")
        x = x.detach()
        E = torch.zeros((), dtype=x.dtype, device=x.device)
        g = torch.zeros_like(x)
        for t in self.terms:
            E = E + t.accumulate_value_grad_hessian_diagonal(x, g, None)
        return E, g

    def constant_hessian_diagonal(self, dtype: torch.dtype, device: torch.device) -> torch.Tensor | None:
        """(V, 3, 3) sum of the Hessian diagonals of the terms whose Hessian is constant
        (:attr:`EnergyTerm.constant_hessian`), computed once per (dtype, device, term state) and cached; None
        if no term has a constant Hessian. Do not modify the result."""
        const = [t for t in self.terms if t.constant_hessian]
        if not const:
            return None
        key = (dtype, torch.device(device), tuple(t.state_key() for t in const))
        cache = self._const_diag
        if cache is None or cache[0] != key:
            x0 = torch.zeros(self.num_vertices, 3, dtype=dtype, device=device)
            h = torch.zeros(self.num_vertices, 3, 3, dtype=dtype, device=device)
            for t in const:
                h.add_(t.hessian_diagonal(x0))
            self._const_diag = cache = (key, h)
        return cache[1]

    def hessian_diagonal(self, x: torch.Tensor) -> torch.Tensor:
        """(V, 3, 3) sum of the terms' Hessian diagonal blocks (each term's default: PSD-projected)."""
        check_positions(x, self.num_vertices, "SimModel")
        x = x.detach()
        const = self.constant_hessian_diagonal(x.dtype, x.device)
        h = (torch.zeros(self.num_vertices, 3, 3, dtype=x.dtype, device=x.device) if const is None
             else const.clone())
        for t in self.terms:
            if not t.constant_hessian:
                h.add_(t.hessian_diagonal(x))
        return h

    def value_grad_hessian_diagonal(
        self, x: torch.Tensor, *, reuse_elastic: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Energy (), gradient (V, 3) and Hessian diagonal blocks (V, 3, 3) together.

        Terms that can share work between them do; terms with a constant Hessian contribute their cached
        diagonal (:meth:`constant_hessian_diagonal`); terms with sparse derivatives (the range-limited
        barrier) touch only their rows.

        Args:
            x: (V, 3) positions in metres.
            reuse_elastic: reuse the diagonal of the non-volatile terms (see
                :attr:`~torchgarment.sim.energies.base.EnergyTerm.volatile_hessian`) from the last call made
                with ``reuse_elastic=False`` (same dtype and device), and evaluate only the volatile terms'
                diagonal (barriers, contact) at ``x``. The result is then the exact diagonal of the volatile
                terms plus a slightly stale one of the elastic terms, which is what a Jacobi preconditioner
                needs. Falls back to a full evaluation when nothing is cached.
        """
        check_positions(x, self.num_vertices, "SimModel")
        x = x.detach()
        E = torch.zeros((), dtype=x.dtype, device=x.device)
        g = torch.zeros_like(x)
        cached = self._elastic_diag
        if reuse_elastic and cached is not None and cached.dtype == x.dtype and cached.device == x.device:
            h = cached.clone()
            for t in self.terms:
                E = E + t.accumulate_value_grad_hessian_diagonal(x, g, h if t.volatile_hessian else None)
            self._record_volatile_rows()
            return E, g, h
        const = self.constant_hessian_diagonal(x.dtype, x.device)
        h = (torch.zeros(self.num_vertices, 3, 3, dtype=x.dtype, device=x.device) if const is None
             else const.clone())
        for t in self.terms:  # elastic (non-volatile) terms first, then the elastic sum is cached
            if not t.volatile_hessian:
                E = E + t.accumulate_value_grad_hessian_diagonal(x, g, None if t.constant_hessian else h)
        self._elastic_diag = h.clone()
        for t in self.terms:
            if t.volatile_hessian:
                E = E + t.accumulate_value_grad_hessian_diagonal(x, g, h)
        self._record_volatile_rows()
        return E, g, h

    def _record_volatile_rows(self) -> None:
        """Set :attr:`last_volatile_rows` from the volatile terms' ``last_hessian_rows``."""
        rows = [t.last_hessian_rows for t in self.terms if t.volatile_hessian]
        if any(r is None for r in rows):
            self.last_volatile_rows = None
        elif not rows:
            self.last_volatile_rows = torch.zeros(0, dtype=torch.long, device=self.device)
        else:
            self.last_volatile_rows = torch.cat(rows) if len(rows) > 1 else rows[0]

    def hessian_blocks(self, x: torch.Tensor, project_psd: bool = True) -> HessianBlocks:
        """Block-COO Hessian of the total energy (the terms' blocks concatenated; duplicates sum)."""
        check_positions(x, self.num_vertices, "SimModel")
        x = x.detach()
        parts = [t.hessian_blocks(x, project_psd=project_psd) for t in self.terms]
        if not parts:
            empty = torch.zeros(0, dtype=torch.long, device=x.device)
            return HessianBlocks(empty, empty.clone(), torch.zeros(0, 3, 3, dtype=x.dtype, device=x.device))
        return HessianBlocks.cat(parts)

    def term_values(self, x: torch.Tensor) -> dict[str, float]:
        """Each term's energy in joules, by name (analytic evaluation, no graph)."""
        check_positions(x, self.num_vertices, "SimModel")
        with torch.no_grad():
            return {t.name: float(t.value_and_grad(x.detach())[0]) for t in self.terms}

    # ------------------------------------------------------------------ barriers
    def max_step(self, x: torch.Tensor, dx: torch.Tensor) -> float:
        """Largest ``alpha`` in (0, 1] keeping every barrier finite along ``x + alpha dx``: the minimum over
        the terms that have a ``max_step`` (SDF barrier, IPC CCD); 1.0 if none does."""
        check_positions(x, self.num_vertices, "SimModel")
        alpha = 1.0
        for t in self.terms:
            if hasattr(t, "max_step"):
                alpha = min(alpha, float(t.max_step(x, dx)))
        return alpha

    def project_feasible(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` with vertices inside the body moved just outside (each term with ``project_feasible`` in
        turn); ``x`` itself when no term has one."""
        check_positions(x, self.num_vertices, "SimModel")
        for t in self.terms:
            if hasattr(t, "project_feasible"):
                x = t.project_feasible(x)
        return x

    def extra_repr(self) -> str:
        return f"num_vertices={self.num_vertices}, terms={list(self.term_names)}, dtype={self.dtype}"


def check_scene_input(garment: GarmentMesh, body_sdf: torch.nn.Module | None = None, *,
                      check_rest: bool = True) -> None:
    """Reject a garment (and body) the simulator cannot handle stably, with a one-line message.

    Checks, vectorized (a few milliseconds at 30K vertices), in float64 whatever the garment's dtype:

    * finite positions ``x`` and rest positions ``p``; at least one face; face indices in ``[0, V)``;
    * units: every bounding-box side of ``x`` and ``p`` at most :data:`MAX_EXTENT` m; with a body SDF that has
      ``bounds`` (a :class:`~torchgarment.sdf.BodySDF`), the body's box at most :data:`MAX_EXTENT` m and the
      garment at most :data:`MAX_GARMENT_TO_BODY` times the body's box (a garment in millimetres on a body in
      metres spans ~1000x the body);
    * with ``check_rest``: the rest geometry (``p`` for a pattern mesh, else ``x``, as the stretch and bend
      terms use it) has no edge shorter than :data:`MIN_REST_EDGE_RATIO` times the median edge and no
      triangle with an angle below :data:`MIN_REST_ANGLE_DEG` (slivers; degenerate triangles have angle 0).

    Args:
        garment: the garment mesh.
        body_sdf: the body's SDF module, or None.
        check_rest: also check rest edges and triangles (needed by STRETCH and BEND).

    Raises:
        InputError: non-finite coordinates; garment or body not in metres.
        MeshError: no faces, face indices out of range, (near-)zero rest edges, sliver or degenerate rest
            triangles.
    """
    g = garment
    V = g.num_vertices
    x = g.x.detach().to(torch.float64)
    if not bool(torch.isfinite(x).all()):
        raise InputError(f"garment positions x contain {int((~torch.isfinite(x)).any(dim=1).sum())} "
                         f"non-finite vertices (NaN or Inf)")
    p = None if g.p is None else g.p.detach().to(torch.float64)
    if p is not None and not bool(torch.isfinite(p).all()):
        raise InputError("garment rest positions p contain NaN or Inf")
    if g.num_faces == 0:
        raise MeshError("the garment has no faces")
    if int(g.faces.min()) < 0 or int(g.faces.max()) >= V:
        raise MeshError(f"garment faces index vertices outside [0, {V}): min {int(g.faces.min())}, "
                        f"max {int(g.faces.max())}")
    # units
    size = float((x.max(dim=0).values - x.min(dim=0).values).max())
    if p is not None:
        size = max(size, float((p.max(dim=0).values - p.min(dim=0).values).max()))
    if size > MAX_EXTENT:
        raise InputError(f"the garment spans {size:.4g} m (more than {MAX_EXTENT:g} m): coordinates must be "
                         f"in metres; {_unit_hint(size)}")
    bounds = getattr(body_sdf, "bounds", None) if body_sdf is not None else None
    if isinstance(bounds, torch.Tensor) and bounds.shape == (2, 3):
        body = float((bounds[1] - bounds[0]).max())
        if body > MAX_EXTENT:
            raise InputError(f"the body SDF spans {body:.4g} m (more than {MAX_EXTENT:g} m): the body must "
                             f"be in metres; {_unit_hint(body)}")
        if body > 0 and size > MAX_GARMENT_TO_BODY * body:
            raise InputError(f"the garment spans {size:.4g} m, {size / body:.0f}x the body's {body:.3g} m: "
                             f"both must be in metres; {_unit_hint(size / body)}")
    if not check_rest:
        return
    rest = p if p is not None else x
    what = "pattern (p)" if p is not None else "rest (x)"
    e = g.edges
    lengths = torch.linalg.vector_norm(rest[e[:, 1]] - rest[e[:, 0]], dim=1)
    k = int(torch.argmin(lengths))
    shortest, median = float(lengths[k]), float(lengths.median())
    if not shortest > 0:
        raise MeshError(f"garment {what} edge {e[k].tolist()} has zero rest length (duplicate vertex "
                        f"positions or a face repeating a vertex); remesh the pattern")
    if shortest < MIN_REST_EDGE_RATIO * median:
        raise MeshError(f"garment {what} edge {e[k].tolist()} is {shortest:.3g} m long, "
                        f"{median / shortest:.3g}x shorter than the median edge ({median:.3g} m; limit "
                        f"{1 / MIN_REST_EDGE_RATIO:g}x): its spring would be that much stiffer; remesh the "
                        "pattern")
    t = rest[g.faces]
    if t.shape[-1] == 2:
        t = torch.cat([t, torch.zeros_like(t[..., :1])], dim=-1)
    sides = torch.stack([t[:, 2] - t[:, 1], t[:, 0] - t[:, 2], t[:, 1] - t[:, 0]], dim=1)  # (F, 3, 3)
    lengths = torch.linalg.vector_norm(sides, dim=2).sort(dim=1).values  # (F, 3) ascending
    twice_area = torch.linalg.vector_norm(torch.linalg.cross(sides[:, 2], -sides[:, 1], dim=1), dim=1)
    sin_min = twice_area / (lengths[:, 1] * lengths[:, 2])  # sine of the angle opposite the shortest side
    f = int(torch.argmin(sin_min))
    angle = math.degrees(math.asin(min(1.0, float(sin_min[f]))))
    if angle < MIN_REST_ANGLE_DEG:
        kind = "degenerate" if angle < 1e-6 else "sliver"
        raise MeshError(f"garment {what} triangle {f} {g.faces[f].tolist()} is {kind}: smallest angle "
                        f"{angle:.3g} deg (limit {MIN_REST_ANGLE_DEG:g} deg); remesh the pattern")


def _unit_hint(ratio: float) -> str:
    if ratio > 200.0:
        return "was it given in millimetres? (multiply by 0.001)"
    return "was it given in centimetres or millimetres? (multiply by 0.01 or 0.001)"


def _as_effects(effects: Iterable[Effect | str]) -> set[Effect]:
    if isinstance(effects, (str, Effect)):
        effects = [effects]
    return {Effect.resolve(e) for e in effects}


def _rest_positions(g: GarmentMesh) -> torch.Tensor:
    """Reference positions for the IPC terms: the flat pattern when there is one (its areas and adjacency)."""
    return (g.p if g.p is not None else g.x).detach()


def _contact_module(effect: Effect) -> ModuleType:
    try:
        return importlib.import_module("torchgarment.sim.contact")
    except ImportError as exc:
        raise InputError(f"effect {effect.value!r} needs torchgarment.sim.contact (IPC via ipctk), which "
                         f"could not be imported: {exc}") from exc
