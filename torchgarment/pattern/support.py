"""What holds a garment up: the support (the paper's sticking line, Wang 2018 Eq. 4's ``F(x)``).

A pattern's :attr:`~torchgarment.pattern.spec.SewingPattern.support` lists (panel, edge) pairs that form one
closed loop of *free* (unstitched) edges once the panels are sewn, e.g. a skirt's waistband. The simulation
sticks the loop's vertices to targets with soft springs (:class:`~torchgarment.sim.energies.pins.Pins`):
in the base drape at the body's waist (:mod:`torchgarment.sim.drape`), in the adjustment at the transferred
base positions (:mod:`torchgarment.adjust.pipeline`).

Free loops: the corners of the panels are merged where stitches join them (an ``OPPOSITE`` stitch joins
``a.start`` with ``b.end`` and ``a.end`` with ``b.start``, a ``SAME`` stitch start with start and end with
end); the unstitched edges then form a graph on the merged corners whose cycles are the garment's openings
(waist, hems, neck, armholes, cuffs).

Proposal rule (:func:`propose_support`, for patterns that declare none): the *topmost* free loop (highest mean
height of its placed 3D edges) is proposed when the pattern is a bottom garment, i.e. when no stitch passes
above that loop: the placed 3D midpoint of every edge of every seam between two *different* panels lies below
the loop's lowest point (+1 mm; darts, stitched within one panel, are not seams that carry the garment). A
shoulder seam joins a front and a back panel above the lowest point of the neck opening (the topmost loop of a
top), so tops, dresses and bodysuits get no proposal (they hang from the shoulders). The loop must also go
round the body (one turn about the vertical axis ``x = z = 0``): the outline of a single unstitched
panel is a closed free loop too, and sticking it held a flat panel in the air.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from torchgarment.errors import InputError, PatternError
from torchgarment.pattern.spec import EdgeRef, SewingPattern, StitchOrientation

if TYPE_CHECKING:
    import torch

    from torchgarment.structures.garment_mesh import GarmentMesh

ABOVE_TOLERANCE = 1e-3
"""A stitch midpoint this far (metres) above the topmost loop's lowest point makes the pattern a top."""


@dataclass(frozen=True)
class LoopEdge:
    """One edge of an ordered loop: the edge and whether the loop runs it from its end to its start."""

    ref: EdgeRef
    reversed: bool


def edge_name(pattern: SewingPattern, ref: EdgeRef) -> str:
    """The name of an edge for :attr:`SewingPattern.support`: its label when unique in the panel, else its
    index."""
    edges = pattern.panels[ref.panel].edges
    label = edges[ref.edge].label
    if label and sum(e.label == label for e in edges) == 1:
        return label
    return str(ref.edge)


def parse_support(spec: str, pattern: SewingPattern) -> tuple[tuple[str, str], ...]:
    """Parse ``PANEL:EDGE[,PANEL:EDGE...]`` (an edge by label or index) against ``pattern``.

    Raises:
        InputError: a malformed item, an unknown panel or edge, an edge named twice, or edges that do not form
            one closed loop of unstitched edges.
    """
    items = [s.strip() for s in str(spec).split(",") if s.strip()]
    if not items:
        raise InputError("--support: give PANEL:EDGE[,PANEL:EDGE...]")
    out = []
    for item in items:
        panel, sep, edge = item.rpartition(":")
        if not sep or not panel or not edge:
            raise InputError(f"--support {item!r}: expected PANEL:EDGE (an edge label or index)")
        try:
            pattern.edge_index(panel, edge)
        except PatternError as exc:
            raise InputError(f"--support {item}: {exc}") from None
        out.append((panel, edge))
    support = tuple(out)
    try:
        ordered_loop(pattern, support)
    except PatternError as exc:
        raise InputError(f"--support {spec}: {exc}") from None
    return support


class _Corners:
    """Union-find over panel corners (panel, vertex index), merged along the stitches."""

    def __init__(self, pattern: SewingPattern) -> None:
        self.parent: dict[tuple[str, int], tuple[str, int]] = {}
        for s in pattern.stitches:
            ea = pattern.panels[s.a.panel].edges[s.a.edge]
            eb = pattern.panels[s.b.panel].edges[s.b.edge]
            pb = (eb.end, eb.start) if s.orientation is StitchOrientation.OPPOSITE else (eb.start, eb.end)
            self.union((s.a.panel, ea.start), (s.b.panel, pb[0]))
            self.union((s.a.panel, ea.end), (s.b.panel, pb[1]))

    def find(self, c: tuple[str, int]) -> tuple[str, int]:
        root = c
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        while c != root:
            c, self.parent[c] = self.parent.get(c, c), root
        return root

    def union(self, a: tuple[str, int], b: tuple[str, int]) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _order(pattern: SewingPattern, refs: list[EdgeRef], corners: _Corners) -> list[LoopEdge] | None:
    """The edges ``refs`` as one closed loop in traversal order (from ``refs[0]`` forwards), or None."""
    ends = {}
    for r in refs:
        e = pattern.panels[r.panel].edges[r.edge]
        ends[r] = (corners.find((r.panel, e.start)), corners.find((r.panel, e.end)))
    node_edges: dict[tuple[str, int], list[EdgeRef]] = {}
    for r, (a, b) in ends.items():
        node_edges.setdefault(a, []).append(r)
        node_edges.setdefault(b, []).append(r)
    if any(len(v) != 2 for v in node_edges.values()) or len(node_edges) != len(refs):
        return None
    loop = [LoopEdge(refs[0], False)]
    node = ends[refs[0]][1]
    while len(loop) < len(refs):
        nxt = [r for r in node_edges[node] if r != loop[-1].ref]
        if not nxt or any(le.ref == nxt[0] for le in loop):
            return None
        r = nxt[0]
        rev = ends[r][1] == node and ends[r][0] != node
        loop.append(LoopEdge(r, rev))
        node = ends[r][0] if rev else ends[r][1]
    return loop if node == ends[refs[0]][0] else None


def ordered_loop(pattern: SewingPattern, support: tuple[tuple[str, str], ...] | None = None
                 ) -> list[LoopEdge]:
    """The support's edges (default ``pattern.support``) as one closed loop in traversal order.

    Raises:
        PatternError: unknown panel or edge, a stitched edge, or edges that do not form one closed loop.
    """
    support = pattern.support if support is None else support
    refs = [EdgeRef(p, pattern.edge_index(p, e)) for p, e in support]
    if len(set(refs)) != len(refs):
        raise PatternError("the support names an edge twice")
    stitched = {r for s in pattern.stitches for r in (s.a, s.b)}
    for r in refs:
        if r in stitched:
            raise PatternError(f"the support edge {r.panel}:{edge_name(pattern, r)} is stitched; a support "
                               "is a loop of unstitched edges")
    loop = _order(pattern, refs, _Corners(pattern)) if refs else None
    if loop is None:
        raise PatternError("the support edges do not form one closed loop once the panels are sewn")
    return loop


def free_loops(pattern: SewingPattern) -> list[list[LoopEdge]]:
    """Every closed loop of unstitched edges (the garment's openings), each in traversal order."""
    corners = _Corners(pattern)
    stitched = {r for s in pattern.stitches for r in (s.a, s.b)}
    free = [EdgeRef(n, i) for n, p in pattern.panels.items() for i in range(len(p.edges))
            if EdgeRef(n, i) not in stitched]
    # connected components of the free edges on the merged corners
    parent: dict[tuple[str, int], tuple[str, int]] = {}

    def find(c: tuple[str, int]) -> tuple[str, int]:
        while parent.setdefault(c, c) != c:
            c = parent[c]
        return c

    ends = {}
    for r in free:
        e = pattern.panels[r.panel].edges[r.edge]
        ends[r] = (corners.find((r.panel, e.start)), corners.find((r.panel, e.end)))
        ra, rb = find(ends[r][0]), find(ends[r][1])
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    by_root: dict[tuple[str, int], list[EdgeRef]] = {}
    for r in free:
        by_root.setdefault(find(ends[r][0]), []).append(r)
    groups = list(by_root.values())
    loops = []
    for refs in groups:
        if refs:
            loop = _order(pattern, refs, corners)
            if loop is not None:
                loops.append(loop)
    return loops


def _placed_points(pattern: SewingPattern, ref: EdgeRef, resolution: int = 16) -> np.ndarray:
    panel = pattern.panels[ref.panel]
    return panel.to_3d(panel.edges[ref.edge].polyline(*panel.edge_endpoints(ref.edge), resolution))


def _turns_around_vertical(points: np.ndarray) -> float:
    """Signed number of turns a closed polyline (P, 3) in placed 3D positions makes around the vertical axis
    ``x = z = 0``, where placed patterns stand round the body: about +-1 for a waistband round the body, 0 for
    the outline of a single panel on one side of it."""
    xz = points[:, [0, 2]]
    angle = np.arctan2(xz[:, 1], xz[:, 0])
    step = np.diff(np.append(angle, angle[0]))
    return float(((step + np.pi) % (2 * np.pi) - np.pi).sum() / (2 * np.pi))


def propose_support(pattern: SewingPattern) -> tuple[tuple[str, str], ...]:
    """The support proposed for a pattern that declares none (see the module docstring for the rule).

    Returns:
        The topmost free loop as (panel, edge name) pairs for a bottom garment; ``()`` for a garment that
        hangs from the shoulders or has no closed free loop.
    """
    loops = free_loops(pattern)
    if not loops:
        return ()
    pts = [np.concatenate([_placed_points(pattern, le.ref) for le in loop]) for loop in loops]
    top = int(np.argmax([p[:, 1].mean() for p in pts]))
    if abs(_turns_around_vertical(pts[top])) < 0.5:
        return ()  # the loop does not go round the body (e.g. the outline of one unstitched panel)
    lowest = float(pts[top][:, 1].min())
    for s in pattern.stitches:
        if s.a.panel == s.b.panel:
            continue
        for ref in (s.a, s.b):
            mid = _placed_points(pattern, ref, 2)[1]
            if mid[1] > lowest + ABOVE_TOLERANCE:
                return ()
    return tuple((le.ref.panel, edge_name(pattern, le.ref)) for le in loops[top])


def choose_support(pattern: SewingPattern, spec: str | None, enabled: bool = True
                   ) -> tuple[SewingPattern, str | None]:
    """The command-line rule (``--support`` / ``--no-support``): the pattern to simulate and a note.

    ``--no-support`` (``enabled`` False) keeps the pattern (the simulation is told not to stick it);
    ``--support SPEC`` replaces the declared support (:func:`parse_support`); otherwise a pattern without a
    support gets :func:`propose_support`'s loop, and the note names it (one line, for stderr).

    Returns:
        ``(pattern, note)``: a copy with the chosen support (or the input), and the note or None.

    Raises:
        InputError: a bad ``spec``.
    """
    from dataclasses import replace

    if not enabled:
        return pattern, None
    if spec is not None:
        return replace(pattern, support=parse_support(spec, pattern)), None
    if pattern.support:
        return pattern, None
    proposed = propose_support(pattern)
    if not proposed:
        return pattern, None
    return replace(pattern, support=proposed), (
        f"support: proposed {format_support(proposed)} (the topmost closed loop of a garment with no seam "
        "over the shoulders); choose another with --support PANEL:EDGE,... or none with --no-support")


def format_support(support: tuple[tuple[str, str], ...]) -> str:
    """``PANEL:EDGE,PANEL:EDGE...`` (the ``--support`` syntax), or ``"none"``."""
    return ",".join(f"{p}:{e}" for p, e in support) if support else "none"


def support_vertices(pattern: SewingPattern, mesh: GarmentMesh,
                     support: tuple[tuple[str, str], ...] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The mesh vertices of the support loop, in loop order, and their rest arc length along the loop.

    Args:
        pattern: the pattern ``mesh`` was made from (``mesh_pattern``: the mesh has its ``layout``).
        mesh: the garment mesh.
        support: default ``pattern.support``.

    Returns:
        ``(indices, s, length)``: (P,) long mesh vertices (each once; the two vertices of a stitched corner
        both appear), (P,) float64 their arc length in metres along the loop, measured in the pattern (rest)
        positions ``mesh.p`` from the loop's first vertex, and the loop's rest length (the meshed polyline's,
        metres).

    Raises:
        PatternError: the support is not a closed loop of free edges; the mesh has no layout.
    """
    import torch

    if mesh.layout is None or mesh.p is None:
        raise PatternError("the support's vertices need a mesh made by mesh_pattern (layout and p)")
    loop = ordered_loop(pattern, support)
    idx, arc = [], []
    s0 = 0.0
    for le in loop:
        run = mesh.layout.run(le.ref.panel, le.ref.edge)
        if le.reversed:
            run = run.flip(0)
        seg = torch.linalg.vector_norm(mesh.p[run[1:]] - mesh.p[run[:-1]], dim=1).double().cpu()
        s = s0 + torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(seg, 0)])
        idx.append(run.cpu())
        arc.append(s)
        s0 = float(s[-1])
    idx_all, arc_all = torch.cat(idx), torch.cat(arc)
    seen: set[int] = set()
    keep = []
    for k, v in enumerate(idx_all.tolist()):
        if v not in seen:
            seen.add(v)
            keep.append(k)
    keep_t = torch.as_tensor(keep, dtype=torch.long)
    return idx_all[keep_t].to(mesh.device), arc_all[keep_t], s0


def support_loop_length(pattern: SewingPattern, support: tuple[tuple[str, str], ...] | None = None) -> float:
    """Rest length in metres of the support loop (sum of its edges' arc lengths)."""
    return float(sum(pattern.panels[le.ref.panel].edge_length(le.ref.edge)
                     for le in ordered_loop(pattern, support)))


__all__ = ["LoopEdge", "choose_support", "edge_name", "format_support", "free_loops", "ordered_loop",
           "parse_support", "propose_support", "support_loop_length", "support_vertices"]
