"""What a benchmark script records besides its own figures: the machine, its load, and its speed in the run.

The project's benchmarks run on shared 2-core machines whose speed changes from hour to hour and from
machine to machine by 2x or more. The same messy retargeting bench (``scripts/bench_retarget.py --messy``,
the same code and cached drapes) took a mean of 36.5 s per pair on 2026-11-29 in a slow hour and 17.4-19.2 s
on a quiet machine on 2026-12-01 (``README.md``, "Retargeting"). A figure held against an absolute target
(seconds per pair) is only comparable across runs together with the machine's speed in the same run, so the
benches record it at their start and end:

* :func:`machine_record`: platform, processor, CPU count, Python and torch versions, torch's threads, and the
  load average (1, 5 and 15 minutes);
* :func:`speed_reference`: two fixed workloads that stand for the two kinds of work in the benches, timed in
  the current torch threads:

  - ``spring_pass_ms``: the energy and gradient of springs on a triangulated square grid of about
    ``spring_vertices`` vertices (default 30K, 3 springs per vertex; :func:`reference_grid`): differences
    and scatters as torch CSR products, norms and elementwise products, the kind of work of
    ``scripts/bench_sim.py``'s baseline (a first version gathered and scattered with index operations, whose
    speed varied by 20 % with where the grid's tensors lay in memory);
  - ``factorization_ms``: one scipy SuperLU factorization (scipy's default ordering and pivoting) of the
    grid's spring Laplacian times the 3x3 identity, slightly shifted, at about ``factor_vertices`` vertices
    (default 5K, a retargeted garment's size): the direct solver's share.

  Both are written with torch and scipy alone, not with the library's springs or factorizations, so that the
  reference stays the same workload when the library gets faster.

Both are medians over repeats (``*_min_ms``: the minima). :class:`MachineWatch` takes both at a bench's
start and end and gives the JSON block and a printed line, with the process's CPU time over the bench's wall
time: the cores it really used (a retargeting run at ``threads=1`` once used 1.47, numpy's BLAS pool spinning
on the second core; ``README.md``, "One thread means one core"). Two runs on different machines or hours
compare through the ratio of their references (the messy bench's seconds per pair against the factorization
and spring pass of the same run). The grids are generated; nothing is read from disk.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import sys
import time
import warnings

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from torchgarment.errors import InputError

__all__ = ["MachineWatch", "load_average", "machine_record", "reference_grid", "speed_reference"]


def load_average() -> tuple[float, float, float]:
    """The system's 1, 5 and 15 minute load averages (NaN where the platform has none)."""
    try:
        a, b, c = os.getloadavg()
    except (AttributeError, OSError):  # Windows has no load average
        return (math.nan, math.nan, math.nan)
    return (float(a), float(b), float(c))


def machine_record() -> dict:
    """Platform, processor, CPU count, Python and torch versions, torch's intra-op threads and the load
    average (a JSON-ready dict)."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "load_average": list(load_average()),
    }


def reference_grid(vertices: int, *,
                   spacing: float = 0.01) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A triangulated ``n x n`` grid (``n = round(sqrt(vertices))``, at least 2) and a deformed state
    (float64).

    The edges are the grid's horizontal, vertical and one diagonal edges (3 per vertex inside, as in a
    triangle mesh) with rest positions ``spacing`` (metres) apart; the state is the grid stretched by 2 % in
    its plane and lifted by a fixed pseudo-random height of up to ``spacing / 4``, so every edge is in
    tension.

    Returns:
        ``(edges, p, x)``: (E, 2) long vertex pairs, (n^2, 2) rest positions and (n^2, 3) positions in metres.
    """
    if not vertices >= 4:
        raise InputError(f"reference_grid needs at least 4 vertices, got {vertices}")
    n = max(2, round(math.sqrt(vertices)))
    idx = torch.arange(n * n).view(n, n)
    edges = torch.cat([
        torch.stack([idx[:, :-1].reshape(-1), idx[:, 1:].reshape(-1)], 1),
        torch.stack([idx[:-1, :].reshape(-1), idx[1:, :].reshape(-1)], 1),
        torch.stack([idx[:-1, :-1].reshape(-1), idx[1:, 1:].reshape(-1)], 1),
    ])
    u = torch.arange(n, dtype=torch.float64) * spacing
    p = torch.stack(torch.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    gen = torch.Generator().manual_seed(0)
    z = (torch.rand(n * n, generator=gen, dtype=torch.float64) - 0.5) * (0.5 * spacing)
    return edges, p, torch.cat([1.02 * p, z.unsqueeze(1)], 1)


def _incidence(edges: torch.Tensor, num_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(D, S)``: torch sparse CSR (64-bit indices) with ``D x = x[i] - x[j]`` (E, V) and ``S = D^T``."""
    E = edges.shape[0]
    ar = torch.arange(E)
    one = torch.ones(E, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        d = torch.sparse_coo_tensor(torch.stack([torch.cat([ar, ar]), torch.cat([edges[:, 0], edges[:, 1]])]),
                                    torch.cat([one, -one]), (E, num_vertices)).coalesce()
        s = torch.sparse_coo_tensor(d.indices().flip(0), d.values(), (num_vertices, E)).coalesce()
        return d.to_sparse_csr(), s.to_sparse_csr()


def _spring_pass(x: torch.Tensor, D: torch.Tensor, S: torch.Tensor, rest: torch.Tensor,
                 k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Energy and gradient (V, 3) of springs with incidence ``D`` (:func:`_incidence`), rest lengths ``rest``
    and stiffness ``k`` (N/m): differences and scatters as CSR products, norms and elementwise products,
    written here with torch alone so that the reference does not change when the library's own springs get
    faster."""
    d = D @ x
    length = torch.linalg.vector_norm(d, dim=1)
    s = length - rest
    return 0.5 * torch.dot(k * s, s), S @ (d * (k * s / length).unsqueeze(1))


def _median_ms(fn: object, repeats: int) -> tuple[float, float]:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts), 1e3 * min(ts)


def speed_reference(*, spring_vertices: int = 30_000, factor_vertices: int = 5_000, spring_repeats: int = 40,
                    factor_repeats: int = 3) -> dict:
    """Time the two reference workloads (see the module docstring) in the current torch threads.

    Args:
        spring_vertices: about how many vertices the spring pass's grid has.
        factor_vertices: about how many vertices the factorized grid has (its matrix is 3x that size).
        spring_repeats, factor_repeats: timed repeats (after 3 untimed spring passes and one untimed
            factorization).

    Returns:
        ``{"spring_pass_ms", "spring_pass_min_ms", "spring_vertices", "factorization_ms",
        "factorization_min_ms", "factor_vertices", "torch_threads"}``.
    """
    if spring_repeats < 1 or factor_repeats < 1:
        raise InputError("speed_reference needs at least one repeat of each workload")
    edges, p, x = reference_grid(spring_vertices)
    D, S = _incidence(edges, x.shape[0])
    rest = torch.linalg.vector_norm(D @ p, dim=1)
    k = 25.0 / rest
    for _ in range(3):
        _spring_pass(x, D, S, rest, k)
    spring_ms, spring_min = _median_ms(lambda: _spring_pass(x, D, S, rest, k), spring_repeats)

    fedges, fp, _ = reference_grid(factor_vertices)
    n = fp.shape[0]
    e = fedges.numpy()
    w = 25.0 / np.linalg.norm(fp.numpy()[e[:, 0]] - fp.numpy()[e[:, 1]], axis=1)
    adj = scipy.sparse.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = adj + adj.T
    lap = scipy.sparse.diags(np.asarray(adj.sum(axis=1)).ravel() * (1.0 + 1e-3)) - adj
    mat = scipy.sparse.kron(lap, scipy.sparse.identity(3), format="csc")

    def factor() -> None:
        scipy.sparse.linalg.splu(mat)  # scipy's defaults (COLAMD, partial pivoting): fixed by scipy alone

    factor()
    fact_ms, fact_min = _median_ms(factor, factor_repeats)
    return {
        "spring_pass_ms": spring_ms,
        "spring_pass_min_ms": spring_min,
        "spring_vertices": int(x.shape[0]),
        "factorization_ms": fact_ms,
        "factorization_min_ms": fact_min,
        "factor_vertices": int(n),
        "torch_threads": torch.get_num_threads(),
    }


class MachineWatch:
    """The ``machine`` block of a bench's JSON: :func:`machine_record` and :func:`speed_reference` when made
    (call it after setting torch's threads, before the timed work), the load average and the reference again
    at :meth:`finish`.

    Args:
        reference: also time the speed reference (about half a second at each end); False records the machine
            and its load only.
    """

    def __init__(self, reference: bool = True) -> None:
        self.start = machine_record()
        self.reference_start = speed_reference() if reference else None
        self._clock = time.perf_counter(), time.process_time()

    def finish(self) -> dict:
        """The JSON-ready block: the start's machine record, ``load_average_end``, ``speed_reference``
        (``{"start": ..., "end": ...}``, None without ``reference``), and ``wall_seconds`` and
        ``cpu_seconds`` (the process's user and system time, all its threads) between the end of the start's
        reference and this call, with ``cores_used`` their ratio."""
        wall, cpu = time.perf_counter() - self._clock[0], time.process_time() - self._clock[1]
        end = speed_reference() if self.reference_start is not None else None
        return self.start | {"load_average_end": list(load_average()),
                             "speed_reference": {"start": self.reference_start, "end": end},
                             "wall_seconds": wall, "cpu_seconds": cpu,
                             "cores_used": cpu / wall if wall > 0 else math.nan}

    @staticmethod
    def describe(block: dict) -> str:
        """One line of a :meth:`finish` block: the load averages and the speed references, start -> end."""
        a, b = block["load_average"][0], block["load_average_end"][0]
        line = f"machine: {block['cpus']} CPUs, load average {a:.2f} -> {b:.2f}"
        if "cores_used" in block:  # blocks written before 2026-12-02 have no CPU time
            line += (f"; this process {block['cpu_seconds']:.1f} s of CPU in {block['wall_seconds']:.1f} s "
                     f"({block['cores_used']:.2f} cores)")
        ref = block["speed_reference"]
        if ref["start"] is None:
            return line
        s, e = ref["start"], ref["end"]
        return (line + f"; speed reference ({s['torch_threads']} thread(s)): {s['spring_vertices']:,}-vertex "
                f"spring pass {s['spring_pass_ms']:.2f} -> {e['spring_pass_ms']:.2f} ms, "
                f"{s['factor_vertices']:,}-vertex factorization {s['factorization_ms']:.0f} -> "
                f"{e['factorization_ms']:.0f} ms")
