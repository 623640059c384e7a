"""The ``--device cuda`` path (issue 14): every command on a GPU against the same command on the CPU, and the
adjoint gradient through a solve on the GPU against finite differences of the whole solve (float64).

The whole module is skipped on a machine without CUDA (CI has none); it runs on a lent GPU machine with
``python -m pytest -q tests/gpu``. The bodies are chart sizes (the body cache serves them without anny) and a
synthetic retargeting case, so nothing here needs ``../shared``.
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING

import pytest
import torch

from torchgarment import cli
from torchgarment.io.mesh import read_obj

if TYPE_CHECKING:
    from pathlib import Path

DEVICE = os.environ.get("TORCHGARMENT_TEST_DEVICE", "cuda")
"""The device under test; ``TORCHGARMENT_TEST_DEVICE=cpu`` runs the module's logic on a machine without a GPU
(CPU against CPU)."""
pytestmark = pytest.mark.skipif(DEVICE.startswith("cuda") and not torch.cuda.is_available(),
                                reason="no CUDA device on this machine")

COARSE = ["--edge-length", "0.05", "--voxel", "0.01", "--no-progress"]


def _vertices(folder: Path) -> torch.Tensor:
    return torch.as_tensor(read_obj(folder / "garment.obj")[0], dtype=torch.float64)


def _metrics(folder: Path) -> dict:
    return json.loads((folder / "metrics.json").read_text())


def _both(tmp_path: Path, argv: list[str]) -> tuple[Path, Path]:
    """Run ``argv`` (without ``--out``/``--device``) on the CPU and on the GPU; the two output folders."""
    outs = []
    for name, device in (("reference", "cpu"), ("device", DEVICE)):
        out = tmp_path / name
        assert cli.main([*argv, "--out", str(out), "--device", device]) == 0
        outs.append(out)
    return outs[0], outs[1]


def test_drape_on_cuda_matches_cpu(tmp_path: Path) -> None:
    cpu, gpu = _both(tmp_path, ["drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12",
                                *COARSE])
    mc, mg = _metrics(cpu), _metrics(gpu)
    assert mg["inside_vertices"] == 0 and mg["converged"] == mc["converged"]
    gap = float((_vertices(cpu) - _vertices(gpu)).norm(dim=1).max())
    print(f"drape: cpu {mc['seconds']:.2f} s, cuda {mg['seconds']:.2f} s, largest difference "
          f"{1e3 * gap:.3f} mm")
    assert gap <= 2e-3


def test_drape_with_jacobi_pcg_on_cuda_matches_the_direct_solver(tmp_path: Path) -> None:
    """The settle stage's Newton by block-Jacobi CG on the device (``--linear-solver jacobi-pcg``: no
    factorization) against the CPU's default (SuperLU): same usable drape, the mean vertex within 0.5 mm (a
    hem may settle on another of its equilibria, see the README's reproducibility floor)."""
    argv = ["drape", "--pattern", "straight_skirt", "--size", "12", "--body", "12", *COARSE]
    ref, dev = tmp_path / "reference", tmp_path / "device"
    assert cli.main([*argv, "--out", str(ref), "--device", "cpu"]) == 0
    assert cli.main([*argv, "--out", str(dev), "--device", DEVICE, "--linear-solver", "jacobi-pcg"]) == 0
    mc, mg = _metrics(ref), _metrics(dev)
    d = (_vertices(ref) - _vertices(dev)).norm(dim=1)
    print(f"drape jacobi-pcg: cpu direct {mc['seconds']:.2f} s, {DEVICE} jacobi-pcg {mg['seconds']:.2f} s, "
          f"mean difference {1e3 * float(d.mean()):.3f} mm, largest {1e3 * float(d.max()):.3f} mm")
    assert mg["inside_vertices"] == 0 and mg["converged"]
    assert float(d.mean()) <= 5e-4


def test_adjust_on_cuda_matches_cpu(tmp_path: Path) -> None:
    cpu, gpu = _both(tmp_path, ["adjust", "--garment", "straight_skirt", "--base-size", "12", "--target-size",
                                "16", "--iterations", "4", "--exact-interval", "2", "--log-dir",
                                str(tmp_path / "tb"), *COARSE])
    pc = json.loads((cpu / "pattern.json").read_text())
    pg = json.loads((gpu / "pattern.json").read_text())
    assert pc.keys() == pg.keys()
    mc, mg = _metrics(cpu), _metrics(gpu)
    print(f"adjust: objective cpu {mc['objective_final']:.6g}, cuda {mg['objective_final']:.6g}; "
          f"seconds cpu {mc.get('seconds')}, cuda {mg.get('seconds')}")
    # The GPU's atomic scatter-adds change the last bits run to run, and a short adjustment amplifies them
    # (the README: a 1e-16 change moved final objectives by -14 % to +18 %). On an H200 the same command gave
    # 2.55 and 2.77 against the CPU's 2.67 (2026-11-26), so the check is that it optimizes as well, not
    # to the bit.
    assert mg["objective_final"] <= 1.15 * mc["objective_final"] + 1e-12


def test_pca_fit_on_cuda_matches_cpu(tmp_path: Path) -> None:
    from torchgarment.body import Body
    from torchgarment.io.mesh import save_obj

    bodies = tmp_path / "bodies"
    for size in ("8", "10", "12", "14", "16"):
        b = Body.from_size(size)
        save_obj(bodies / f"{size}.obj", b.vertices, b.faces)
    model = tmp_path / "model"
    assert cli.main(["pca", "build", "--garment", "straight_skirt", "--dataset", str(bodies), "--k", "2",
                     "--cache", str(tmp_path / "cache"), "--out", str(model), *COARSE]) == 0
    held_out = Body.from_size("20")
    save_obj(tmp_path / "20.obj", held_out.vertices, held_out.faces)
    cpu, gpu = _both(tmp_path, ["pca", "fit", "--model", str(model), "--body", str(tmp_path / "20.obj"),
                                "--push-out", "--refine", "20"])
    gap = float((_vertices(cpu) - _vertices(gpu)).norm(dim=1).max())
    mg = _metrics(gpu)
    print(f"pca fit: largest cpu/cuda difference {1e3 * gap:.4f} mm; cuda seconds {mg['seconds']}")
    assert mg["penetrations"]["inside_after_push_out"] == 0
    assert gap <= 1e-3


def _grid_panel(n: int, m: int, h: float, x0: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(rest positions (N, 2), faces (F, 3)) of an n x m grid of squares of side h, split into triangles."""
    ij = torch.cartesian_prod(torch.arange(n + 1), torch.arange(m + 1))
    p = torch.stack([x0 + h * ij[:, 0], h * ij[:, 1]], dim=1).to(torch.float64)
    vid = torch.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    a, b = vid[:-1, :-1].reshape(-1), vid[1:, :-1].reshape(-1)
    c, d = vid[1:, 1:].reshape(-1), vid[:-1, 1:].reshape(-1)
    return p, torch.cat([torch.stack([a, b, c], 1), torch.stack([a, c, d], 1)])


def _scene_on(device: str, case: str, sdf: object | None) -> tuple[torch.nn.Module, torch.Tensor]:
    """(model, x0) on ``device``: a sheet pinned to stretched, wavy targets, falling on a sphere ("barrier")
    or two sheets sewn together ("sew")."""
    from torchgarment.sim import Material, Scene
    from torchgarment.structures.garment_mesh import GarmentMesh

    n, h = 6, 0.02
    if case == "sew":
        pa, fa = _grid_panel(4, n, h)
        pb, fb = _grid_panel(4, n, h, x0=4 * h + 0.01)
        p = torch.cat([pa, pb])
        faces = torch.cat([fa, fb + pa.shape[0]])
        ids = torch.cat([torch.zeros(len(fa), dtype=torch.long), torch.ones(len(fb), dtype=torch.long)])
        seams = torch.stack([torch.arange(4 * (n + 1), 5 * (n + 1)), pa.shape[0] + torch.arange(n + 1)], 1)
        x = torch.stack([p[:, 0], torch.zeros(len(p), dtype=torch.float64), p[:, 1]], 1)
        mesh = GarmentMesh(x, faces, p=p, panel_ids=ids, panel_names=["a", "b"], seam_pairs=seams)
        effects = {"stretch", "pins", "sew"}
    else:
        p, faces = _grid_panel(n, n, h)
        x = torch.stack([p[:, 0], torch.full((len(p),), 0.012, dtype=torch.float64), p[:, 1]], 1)
        mesh = GarmentMesh(x, faces, p=p)
        effects = {"stretch", "pins", "gravity", "body_barrier"}
    on_edge = (p[:, 0] <= 1e-9) | (p[:, 0] >= p[:, 0].max() - 1e-9) | (p[:, 1] <= 1e-9) | \
        (p[:, 1] >= p[:, 1].max() - 1e-9)
    pins = torch.nonzero(on_edge).reshape(-1)
    targets = mesh.x[pins] * torch.tensor([1.1, 1.0, 1.1], dtype=torch.float64)  # stretched 10 %
    targets[:, 1] = 0.01 * torch.sin(20.0 * targets[:, 0]) if case == "sew" else 0.0
    mesh = mesh.to(device)
    scene = Scene(mesh, body_sdf=sdf if case != "sew" else None, pin_indices=pins.to(device),
                  pin_targets=targets.to(device), effects=effects,
                  material=Material(barrier_mu=1e-3, density=2.0))
    return scene.build(), mesh.x


@pytest.mark.parametrize("linear_solver", ["cg", "sparse"])
def test_adjoint_gradient_on_cuda_matches_finite_differences(linear_solver: str) -> None:
    """Directional derivatives of ``L = sum(w * x*(p))`` through the solve on the GPU (adjoint) against
    central differences of the whole solve, for a sewn and a barrier case (float64)."""
    import trimesh

    from torchgarment.sdf import BodySDF, SDFSettings
    from torchgarment.sim.diff import DifferentiableSolver
    from torchgarment.sim.solvers import SolveSettings

    m = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    m.apply_translation([0.06, -0.045, 0.06])
    sdf = BodySDF.from_mesh(m.vertices, m.faces, SDFSettings(voxel_size=0.004), device=DEVICE)
    tight = SolveSettings(rtol=0.0, atol=1e-11, max_iterations=200)
    gen = torch.Generator().manual_seed(0)
    eps = 1e-6
    for case in ("sew", "barrier"):
        model, x0 = _scene_on(DEVICE, case, sdf)
        layer = DifferentiableSolver(model, x0, tight, linear_solver=linear_solver)
        base = model.get_parameter(layer._slot("p").path).detach().clone()
        x = layer(p=base)
        assert x.device.type == torch.device(DEVICE).type
        w = torch.randn(x.shape, dtype=torch.float64, generator=gen).to(DEVICE)
        theta = base.clone().requires_grad_(True)
        (w * layer(p=theta)).sum().backward()
        assert theta.grad is not None and theta.grad.device.type == torch.device(DEVICE).type
        for _ in range(2):
            v = torch.randn(base.shape, dtype=torch.float64, generator=gen).to(DEVICE)
            v = v / v.abs().max() * base.abs().max()
            with torch.no_grad():
                plus = float((w * layer(p=base + eps * v)).sum())
                fd = (plus - float((w * layer(p=base - eps * v)).sum())) / (2.0 * eps)
            ad = float((theta.grad * v).sum())
            err = abs(ad - fd) / max(abs(fd), 1e-12)
            print(f"cuda {case}/{linear_solver}: adjoint {ad:.8g}, finite differences {fd:.8g}, relative "
                  f"error {err:.2e}")
            assert err <= 1e-4
