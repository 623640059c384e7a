"""One Warp kernel per :class:`~torchgarment.sdf.grid.BodySDF` query on the CPU.

A query of the torch implementation (:meth:`BodySDF._query_block`, :meth:`BodySDF._query_quadratic`) is about
60 (trilinear) or 90 (quadratic) tensor operations, each with its own dispatch and temporaries: at the sizes
of a drape (a few hundred to a few thousand garment vertices) the dispatch is most of the cost, and the SDF
queries were the largest single item of a drape's profile. Here the same arithmetic runs as one Warp launch
per query, point by point.

The kernels repeat the torch code's floating-point operations in the same order (Warp's CPU code does not
contract them into fused multiply-adds). Trilinear float64 queries inside the grid box return the same bits as
the torch path. Elsewhere the two differ by a few units in the last place, because torch groups some sums
differently depending on the batch: the 8 samples of a quadratic query (a lone point is summed another way
than a point in a batch), the far field's distance, float32 sums (accumulated in float64 in some loops, in
float32 in others). The kernels always sum in one order, so a point's value does not depend on the points
queried with it (the lazy barrier queries changing subsets of a garment). A drape's path is sensitive to
such round-off: a hanging hem can settle on another equilibrium, millimetres away, exactly as after any change
of its input's last bits.

The torch path stays the reference and serves what the kernels do not: CUDA tensors (keep tensor code
device-agnostic; there the parallel torch operations do not pay the same dispatch) and grids whose brick edge
is not a power of two or whose node count needs int64 indices.

Shapes: query points ``x`` (N, 3) in the SDF's dtype; outputs ``phi`` (N,) in metres and its gradient (N, 3),
unitless.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch

from torchgarment.warp_runtime import import_warp

if TYPE_CHECKING:
    from torchgarment.sdf.grid import BodySDF

_KERNELS: dict[str, object] = {}
_LAUNCH_LOCK = threading.Lock()  # a recorded launch is shared by an SDF's views: one query at a time


def _kernels() -> dict[str, object]:
    """The two generic kernels (trilinear, quadratic), defined on first use (Warp compiles them then, and
    caches the binaries on disk)."""
    if _KERNELS:
        return _KERNELS
    wp = import_warp()

    @wp.func
    def sample(  # noqa: ANN202 (Warp infers the generic vector it returns)
               px: Any, py: Any, pz: Any, origin: wp.array(dtype=Any), h: Any, box_max: wp.array(dtype=Any),
               cell_max: wp.array(dtype=wp.int32), shift: wp.int32, bstr: wp.array(dtype=wp.int32),
               cell_base: wp.array(dtype=wp.int32), fine_end: wp.int32, nstr: wp.array(dtype=wp.int32),
               nodes: wp.array(dtype=Any), corner: wp.array(dtype=wp.int32), cs_fine: Any, cs_coarse: Any,
               tiny: Any):
        """(phi, dphi/dx, dphi/dy, dphi/dz) of the trilinear interpolant at one point (see
        ``BodySDF._query_block``, whose operations this repeats in order)."""
        zero = h - h
        bsize = wp.int32(1) << shift
        u0 = (px - origin[0]) / h
        u1 = (py - origin[1]) / h
        u2 = (pz - origin[2]) / h
        c0 = wp.min(wp.max(u0, zero), box_max[0])
        c1 = wp.min(wp.max(u1, zero), box_max[1])
        c2 = wp.min(wp.max(u2, zero), box_max[2])
        i0 = wp.min(wp.int32(c0), cell_max[0])
        i1 = wp.min(wp.int32(c1), cell_max[1])
        i2 = wp.min(wp.int32(c2), cell_max[2])
        b0 = i0 >> shift
        b1 = i1 >> shift
        b2 = i2 >> shift
        base = cell_base[b0 * bstr[0] + b1 * bstr[1] + b2 * bstr[2]]
        fl = type(h)(bsize)
        t0 = c0 / fl - type(h)(b0)
        t1 = c1 / fl - type(h)(b1)
        t2 = c2 / fl - type(h)(b2)
        cs = cs_coarse
        if base < fine_end:
            mask = bsize - wp.int32(1)
            base = base + ((i0 & mask) * nstr[0] + (i1 & mask) * nstr[1] + (i2 & mask) * nstr[2])
            t0 = c0 - type(h)(i0)
            t1 = c1 - type(h)(i1)
            t2 = c2 - type(h)(i2)
            cs = cs_fine
        v000 = nodes[corner[0] + base]
        v001 = nodes[corner[1] + base]
        v010 = nodes[corner[2] + base]
        v011 = nodes[corner[3] + base]
        v100 = nodes[corner[4] + base]
        v101 = nodes[corner[5] + base]
        v110 = nodes[corner[6] + base]
        v111 = nodes[corner[7] + base]
        # along z: values and d/dz per (i, j)
        d00 = v001 - v000
        d01 = v011 - v010
        d10 = v101 - v100
        d11 = v111 - v110
        z00 = d00 * t2 + v000
        z01 = d01 * t2 + v010
        z10 = d10 * t2 + v100
        z11 = d11 * t2 + v110
        # along y: values, d/dz and d/dy per i
        dv0 = z01 - z00
        dv1 = z11 - z10
        dz0 = d01 - d00
        dz1 = d11 - d10
        yv0 = dv0 * t1 + z00
        yv1 = dv1 * t1 + z10
        yz0 = dz0 * t1 + d00
        yz1 = dz1 * t1 + d10
        # along x
        xv = yv1 - yv0
        xz = yz1 - yz0
        xy = dv1 - dv0
        phi = xv * t0 + yv0
        g0 = xv / cs
        g1 = (xy * t0 + dv0) / cs
        g2 = (xz * t0 + yz0) / cs
        if u0 != c0 or u1 != c1 or u2 != c2:  # outside the box: phi(p) + |x - p|
            o0 = (u0 - c0) * h
            o1 = (u1 - c1) * h
            o2 = (u2 - c2) * h
            # torch sums float32 in float64 on the CPU (its accumulation type): the same here
            dist = wp.sqrt(type(h)(wp.float64(o0 * o0) + wp.float64(o1 * o1) + wp.float64(o2 * o2)))
            phi = phi + dist
            dd = wp.max(dist, tiny)
            if u0 != c0:
                g0 = o0 / dd
            if u1 != c1:
                g1 = o1 / dd
            if u2 != c2:
                g2 = o2 / dd
        return wp.vector(phi, g0, g1, g2)

    @wp.kernel(enable_backward=False)
    def trilinear(x: wp.array2d(dtype=Any), origin: wp.array(dtype=Any), h: Any, box_max: wp.array(dtype=Any),
                  cell_max: wp.array(dtype=wp.int32), shift: wp.int32, bstr: wp.array(dtype=wp.int32),
                  cell_base: wp.array(dtype=wp.int32), fine_end: wp.int32, nstr: wp.array(dtype=wp.int32),
                  nodes: wp.array(dtype=Any), corner: wp.array(dtype=wp.int32), cs_fine: Any, cs_coarse: Any,
                  tiny: Any, phi: wp.array(dtype=Any), grad: wp.array2d(dtype=Any)) -> None:
        i = wp.tid()
        r = sample(x[i, 0], x[i, 1], x[i, 2], origin, h, box_max, cell_max, shift, bstr, cell_base, fine_end,
                   nstr, nodes, corner, cs_fine, cs_coarse, tiny)
        phi[i] = r[0]
        grad[i, 0] = r[1]
        grad[i, 1] = r[2]
        grad[i, 2] = r[3]

    @wp.kernel(enable_backward=False)
    def quadratic(x: wp.array2d(dtype=Any), origin: wp.array(dtype=Any), h: Any, box_max: wp.array(dtype=Any),
                  cell_max: wp.array(dtype=wp.int32), shift: wp.int32, bstr: wp.array(dtype=wp.int32),
                  cell_base: wp.array(dtype=wp.int32), fine_end: wp.int32, nstr: wp.array(dtype=wp.int32),
                  nodes: wp.array(dtype=Any), corner: wp.array(dtype=wp.int32), cs_fine: Any, cs_coarse: Any,
                  tiny: Any, phi_out: wp.array(dtype=Any), grad: wp.array2d(dtype=Any)) -> None:
        """``BodySDF._query_quadratic`` at one point: 8 trilinear samples, weights and their derivatives, in
        that method's order of operations."""
        i = wp.tid()
        half = type(h)(0.5)
        u0 = (x[i, 0] - origin[0]) / h
        u1 = (x[i, 1] - origin[1]) / h
        u2 = (x[i, 2] - origin[2]) / h
        m0 = wp.floor(u0 + half)
        m1 = wp.floor(u1 + half)
        m2 = wp.floor(u2 + half)
        s0 = u0 - m0
        s1 = u1 - m1
        s2 = u2 - m2
        # per axis: sample coordinate (in voxels) and weight of the lower (l) and upper (u) piece
        al0 = (u0 - half + m0) * half
        al1 = (u1 - half + m1) * half
        al2 = (u2 - half + m2) * half
        au0 = (u0 + half + m0) * half
        au1 = (u1 + half + m1) * half
        au2 = (u2 + half + m2) * half
        wl0 = half - s0
        wl1 = half - s1
        wl2 = half - s2
        wu0 = half + s0
        wu1 = half + s1
        wu2 = half + s2
        phi = h - h
        t0 = h - h
        t1 = h - h
        t2 = h - h
        q0 = h - h
        q1 = h - h
        q2 = h - h
        for c in range(8):  # corner (ci, cj, ck) in _CORNERS order: k fastest
            ci = (c >> 2) & 1
            cj = (c >> 1) & 1
            ck = c & 1
            p0 = al0
            w0 = wl0
            if ci == 1:
                p0 = au0
                w0 = wu0
            p1 = al1
            w1 = wl1
            if cj == 1:
                p1 = au1
                w1 = wu1
            p2 = al2
            w2 = wl2
            if ck == 1:
                p2 = au2
                w2 = wu2
            r = sample(p0 * h + origin[0], p1 * h + origin[1], p2 * h + origin[2], origin, h, box_max,
                       cell_max, shift, bstr, cell_base, fine_end, nstr, nodes, corner, cs_fine, cs_coarse,
                       tiny)
            wprod = w0 * w1 * w2
            phi = phi + wprod * r[0]
            # d wprod / d u_d = sign_d * (product of the other two weights), sign -1 (lower) or +1 (upper)
            e0 = w1 * w2
            e1 = w0 * w2
            e2 = w0 * w1
            if ci == 0:
                e0 = -e0
            if cj == 0:
                e1 = -e1
            if ck == 0:
                e2 = -e2
            t0 = t0 + e0 * r[0]
            t1 = t1 + e1 * r[0]
            t2 = t2 + e2 * r[0]
            q0 = q0 + wprod * r[1]
            q1 = q1 + wprod * r[2]
            q2 = q2 + wprod * r[3]
        phi_out[i] = phi
        grad[i, 0] = t0 / h + half * q0
        grad[i, 1] = t1 / h + half * q1
        grad[i, 2] = t2 / h + half * q2

    _KERNELS["trilinear"] = trilinear
    _KERNELS["quadratic"] = quadratic
    return _KERNELS


def supported(sdf: BodySDF, x: torch.Tensor) -> bool:
    """Whether :func:`query` serves this SDF and these points: CPU float32/float64, int32 indices, a brick
    edge that is a power of two."""
    return (x.device.type == "cpu" and sdf.dtype in (torch.float32, torch.float64)
            and sdf.cell_base.dtype == torch.int32 and sdf._brick_shift is not None)


@dataclass
class _WarpState:
    """What the kernels need of one SDF's buffers, cached on the SDF (``_warp_constants``).

    Attributes:
        key: the buffers' data pointers and dtype (a ``.to()`` makes new buffers and so a new state).
        args: the kernels' arguments between ``x`` and the outputs (Warp arrays and typed scalars).
        tensors: the (contiguous) buffers the arrays view, kept alive with them.
        launches: the recorded launch of each sampling (``quadratic`` True / False), see :func:`query`.
    """

    key: tuple
    args: list
    tensors: list
    launches: dict = field(default_factory=dict)


def _state(sdf: BodySDF) -> _WarpState:
    """The SDF's :class:`_WarpState`, made on its first query and after its buffers change."""
    key = (sdf.nodes.data_ptr(), sdf.cell_base.data_ptr(), sdf.origin.data_ptr(), sdf.dtype)
    cached = sdf.__dict__.get("_warp_constants")
    if cached is not None and cached.key == key:
        return cached
    wp = import_warp()
    scalar = wp.float64 if sdf.dtype == torch.float64 else wp.float32
    tensors = [t.contiguous() for t in (sdf.origin, sdf.box_max, sdf.cell_max, sdf.brick_strides,
                                        sdf.cell_base, sdf.node_strides, sdf.nodes, sdf.corner_offsets)]
    origin, box_max, cell_max, bstr, cell_base, nstr, nodes, corner = (wp.from_torch(t.reshape(-1))
                                                                        for t in tensors)
    args = [origin, scalar(sdf.voxel_size), box_max, cell_max, wp.int32(sdf._brick_shift), bstr, cell_base,
            wp.int32(sdf._fine_end), nstr, nodes, corner, scalar(float(sdf.cell_sizes[0])),
            scalar(float(sdf.cell_sizes[1])), scalar(torch.finfo(sdf.dtype).tiny)]
    state = _WarpState(key, args, tensors)
    sdf.__dict__["_warp_constants"] = state
    return state


def query(sdf: BodySDF, x: torch.Tensor, quadratic: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """``(phi (N,), grad (N, 3))`` at checked points ``x`` (N, 3) in the SDF's dtype (see the module docstring
    for how they compare with the torch path); only where :func:`supported`.

    The first query of an SDF records its launch (Warp resolves the generic kernel's types then); later ones
    only swap the point and output arrays and the size: about 0.15 ms of fixed cost per query.
    """
    wp = import_warp()
    n = x.shape[0]
    phi, grad = torch.empty(n, dtype=x.dtype), torch.empty(n, 3, dtype=x.dtype)
    if n == 0:
        return phi, grad
    arrays = (wp.from_torch(x.detach().contiguous()), wp.from_torch(phi), wp.from_torch(grad))
    state = _state(sdf)
    with _LAUNCH_LOCK:
        cmd = state.launches.get(quadratic)
        if cmd is None:
            cmd = wp.launch(_kernels()["quadratic" if quadratic else "trilinear"], dim=n, device="cpu",
                            inputs=[arrays[0], *state.args, *arrays[1:]], record_cmd=True)
            state.launches[quadratic] = cmd
        else:  # the arguments: x, the state's args, phi, grad
            out = 1 + len(state.args)
            for index, array in zip((0, out, out + 1), arrays, strict=True):
                cmd.set_param_at_index(index, array)
            cmd.set_dim(n)
        cmd.launch()
    return phi, grad
