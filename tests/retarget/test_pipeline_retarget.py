"""End-to-end retargeting: zero intersections, positive distance, metrics, multi-layer."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import igl
import ipctk
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from retarget_synth import pocketed_tube  # noqa: E402

from torchgarment.errors import InputError  # noqa: E402
from torchgarment.retarget.avatars import toy_case
from torchgarment.retarget.inputs import problem_from_arrays
from torchgarment.retarget.pipeline import (
    FitTarget,
    RetargetSettings,
    check_result,
    layer_problem,
    retarget,
)

if TYPE_CHECKING:
    from torchgarment.retarget.inputs import RetargetProblem
    from torchgarment.retarget.pipeline import RetargetResult


def _problem(**kw: object) -> RetargetProblem:
    c = toy_case(**kw)
    return problem_from_arrays(
        c.garment_vertices,
        c.garment_faces,
        c.source_skeleton,
        c.target_vertices,
        c.target_faces,
        c.target_skeleton,
        source_avatar=(c.source_vertices, c.source_faces),
    )


def _ipctk_checks(
    garment: torch.Tensor, faces: torch.Tensor, avatar: torch.Tensor, avatar_faces: torch.Tensor
) -> tuple[bool, bool, float]:
    """Independent ipctk checks in the target frame: garment+avatar (avatar-avatar ignored) and garment
    alone."""
    n = garment.shape[0]
    gf = faces.numpy().astype(np.int32)
    v = np.asfortranarray(np.concatenate([garment.numpy(), avatar.numpy()]))
    f = np.concatenate([gf, avatar_faces.numpy().astype(np.int32) + n])
    mesh = ipctk.CollisionMesh(v, ipctk.edges(f), f)
    mesh.can_collide = ipctk.make_static_obstacle_filter(n)
    gv = np.asfortranarray(garment.numpy())
    gmesh = ipctk.CollisionMesh(gv, ipctk.edges(gf), gf)
    col = ipctk.NormalCollisions()
    col.build(mesh, v, 0.05)
    dmin = math.sqrt(col.compute_minimum_distance(mesh, v)) if len(col) else math.inf
    return bool(ipctk.has_intersections(mesh, v)), bool(ipctk.has_intersections(gmesh, gv)), dmin


@pytest.fixture(scope="module")
def toy_result(tmp_path_factory: pytest.TempPathFactory) -> tuple[RetargetProblem, RetargetResult, Path]:
    p = _problem(target_scale=1.3, target_offset=(2.0, -1.0, 0.5))  # a bigger avatar elsewhere
    log = tmp_path_factory.mktemp("tb")
    return p, retarget(p, progress=False, log_dir=log), log


def test_toy_retarget_is_intersection_free(toy_result: tuple) -> None:
    p, r, _ = toy_result
    av = p.to_work.inverse(p.avatar_vertices)
    inter_av, inter_self, dmin = _ipctk_checks(r.garment_vertices, r.garment_faces, av, p.avatar_faces)
    assert not inter_av and not inter_self
    assert dmin > 0
    m = r.metrics
    assert m["intersections"] == 0 and m["min_distance_mm"] > 0 and m["t_snap"] <= 1.0
    # the garment moved with the avatar (target frame: scaled 1.3 and offset)
    assert torch.allclose(r.garment_vertices.mean(0), p.to_work.inverse(r.work_vertices).mean(0))
    assert float((r.garment_vertices.mean(0) - av.mean(0)).norm()) < 0.3
    for key in ("seconds", "newton_iterations", "grad_norm", "distortion_mean", "distortion_max", "terms"):
        assert key in m
    assert set(m["terms"]) == {"surf", "pos", "curve", "contact", "fit"}
    assert r.distortion.shape == (r.garment_faces.shape[0],) and float(r.distortion.min()) >= 0
    assert m["distortion_max"] >= m["distortion_mean"] > 0
    # the inflation's closest pair, from its per-iteration history (human scale, mm)
    inflate = next(s for s in r.steps if s["step"] == "inflate")
    closest = min((h["min_distance"] for h in r.history if h["stage"] == "inflate"), default=math.inf)
    assert inflate["min_distance_mm"] == 1000.0 * closest and 0 < inflate["min_distance_mm"]
    # how far the fit's last steps moved the garment: the largest step of its last 3 (human scale, mm)
    fit = next(s for s in r.steps if s["step"] == "fit")
    moves = [h["max_displacement"] for h in r.history if h["stage"] == "fit"]
    assert len(moves) == fit["newton_iterations"] > 3
    assert fit["final_motion_mm"] == 1000.0 * max(moves[-3:]) and fit["final_motion_mm"] < 1000.0 * max(moves)


def test_adaptive_stiffness_keeps_the_closest_pairs_apart(toy_result: tuple) -> None:
    """IPC's stiffness update fires when a pair comes within 0.1 dhat and keeps coming closer, so kappa rises
    during the run and the result keeps its closest pair near dhat (2 mm at human scale). With the rule
    handed unsquared distances (it compares squared ones) kappa never rose and this result's closest pair
    was 0.001 mm."""
    _, r, _ = toy_result
    kappas = [h["stiffness"] for h in r.history]
    assert max(kappas) > kappas[0]
    assert all(b >= a for a, b in zip(kappas, kappas[1:]))  # IPC's kappa only grows
    assert r.metrics["min_distance_mm"] > 0.2


def test_tensorboard_scalars_written(toy_result: tuple) -> None:
    _, r, log = toy_result
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ea = EventAccumulator(str(log))
    ea.Reload()
    tags = set(ea.Tags()["scalars"])
    for tag in ("inflate/t", "inflate/alpha", "inflate/term/surf", "fit/min_distance", "fit/term/fit"):
        assert tag in tags
    ts = [e.value for e in ea.Scalars("inflate/t")]
    assert ts[-1] > ts[0]
    assert len(r.history) == r.metrics["newton_iterations"]


@pytest.mark.slow
def test_fit_weight_controls_tightness() -> None:
    p = _problem()
    loose = retarget(p, RetargetSettings(w_fit=0.0), progress=False)
    tight = retarget(p, RetargetSettings(w_fit=20.0), progress=False)
    from torchgarment.sdf.build import SDFSettings
    from torchgarment.sdf.grid import BodySDF

    sdf = BodySDF.from_mesh(p.avatar_vertices, p.avatar_faces, SDFSettings(voxel_size=0.01))
    m = p.fit_mask
    gap = lambda r: float(sdf(r.work_vertices[m]).abs().mean())  # noqa: E731
    assert gap(tight) < gap(loose)
    assert loose.metrics["intersections"] == tight.metrics["intersections"] == 0


def test_source_gap_fit_keeps_a_layer_above_the_cloth_under_it() -> None:
    """FitTarget: by default (a source avatar given) the fit keeps each vertex's source gap, so a band lying
    1 cm over a close-fitting tube stays about 1 cm above it; the surface target pulls both onto the avatar
    and squeezes the band onto the tube (the messy bench's pockets: 1.4 mm left of 4 mm)."""
    from torchgarment.retarget.avatars import tube_mesh

    c = toy_case(target_scale=1.3, target_offset=(2.0, -1.0, 0.5))
    gv, gf = tube_mesh(0.29, 0.23, -0.2, 1.25, 24, 10)  # 1-3 cm from the source torso where it is closest
    off = 0.01
    bv, bf = tube_mesh(0.29 + off, 0.23 + off, 0.35, 0.75, 24, 4)  # a separate band 1 cm outside
    n = gv.shape[0]
    p = problem_from_arrays(torch.cat([gv, bv]), torch.cat([gf, bf + n]), c.source_skeleton,
                            c.target_vertices, c.target_faces, c.target_skeleton,
                            source_avatar=(c.source_vertices, c.source_faces))
    assert float(p.fit_mask[n:].double().mean()) > 0.7  # the band is in the fit region (72 of 96)

    def band_height(r: RetargetResult) -> float:
        x = r.work_vertices.numpy()
        sq, _, _ = igl.point_mesh_squared_distance(x[n:], x[:n], gf.numpy())
        return float(np.median(np.sqrt(sq)))

    keep = retarget(p, progress=False)
    onto = retarget(p, RetargetSettings(fit_target="surface"), progress=False)
    assert keep.metrics["fit_target"] == "source-gap" and onto.metrics["fit_target"] == "surface"
    assert keep.metrics["intersections"] == onto.metrics["intersections"] == 0
    assert 0.7 * off < band_height(keep) < 1.3 * off
    assert band_height(onto) < 0.3 * off
    # the fit vertices end at their targets: within a millimetre (human scale) at the median
    assert keep.metrics["fit_gap_mm"]["miss_median"] < 1.0


def test_a_patch_pocket_stays_where_it_was_sewn() -> None:
    """A pocket that is its own piece lies 4 mm over the front of a tube; retargeted onto a larger avatar it
    keeps its place on the tube (Attachment). Without the term nothing holds it around the body: the shape
    terms are blind to its rigid motions and the positional term holds only its rim's coordinate along a bone
    (the messy bench's pockets slid 2-19 cm before it)."""
    from torchgarment.retarget.objectives import Attachment

    c = toy_case(target_scale=1.3, target_offset=(2.0, -1.0, 0.5))
    v, f, _, m = pocketed_tube(ring=False)
    p = problem_from_arrays(v, f, c.source_skeleton, c.target_vertices, c.target_faces, c.target_skeleton,
                            source_avatar=(c.source_vertices, c.source_faces))
    place = Attachment(p.garment_vertices, p.garment_faces, 0.01, 1.0)  # the pocket's places on the tube
    assert len(place.vertices) == m
    slide = lambda r: float(place.residuals(r.work_vertices).norm(dim=1).median())  # noqa: E731
    held = retarget(p, progress=False)
    free = retarget(p, RetargetSettings(w_attach=0.0), progress=False)
    assert held.metrics["intersections"] == free.metrics["intersections"] == 0
    assert held.metrics["attached_vertices"] == m and free.metrics["attached_vertices"] == 0
    assert free.metrics["attach_miss_mm"] is None
    assert slide(held) < 2e-3  # measured 0.11 mm (work frame: a 1.45 m model)
    assert slide(free) > 1e-2  # measured 2.7 cm
    assert held.metrics["attach_miss_mm"]["median"] < 2.0
    assert held.metrics["distortion_mean"] < 1.5 * free.metrics["distortion_mean"]  # 0.0116 against 0.0111


def test_retarget_onto_the_source_avatar_leaves_the_garment_in_place() -> None:
    """With the source gaps as the fit's targets a garment retargeted onto its own source avatar stays where
    it was (a retarget adds no change of its own); the surface target pulls the fit region onto the body."""
    from torchgarment.retarget.avatars import tube_mesh

    c = toy_case()
    gv, gf = tube_mesh(0.29, 0.23, -0.2, 1.25, 24, 10)
    p = problem_from_arrays(gv, gf, c.source_skeleton, c.source_vertices, c.source_faces, c.source_skeleton,
                            source_avatar=(c.source_vertices, c.source_faces))
    keep = retarget(p, progress=False)
    onto = retarget(p, RetargetSettings(fit_target="surface"), progress=False)
    moved = lambda r: float((r.garment_vertices - gv).norm(dim=1).max())  # noqa: E731
    assert keep.metrics["intersections"] == onto.metrics["intersections"] == 0
    assert moved(keep) < 1e-3  # measured 0.2 mm on a 1.45 m model
    assert moved(onto) > 0.02  # measured 4.8 cm


def test_fit_target_needs_a_source_avatar_for_source_gaps() -> None:
    c = toy_case()
    p = problem_from_arrays(c.garment_vertices, c.garment_faces, c.source_skeleton, c.target_vertices,
                            c.target_faces, c.target_skeleton)
    assert FitTarget.resolve("auto").for_problem(p) is FitTarget.SURFACE
    assert FitTarget.resolve("gap") is FitTarget.SOURCE_GAP
    with pytest.raises(InputError, match="needs the source avatar"):
        retarget(p, RetargetSettings(fit_target="source-gap"), progress=False)
    with pytest.raises(InputError, match="unknown fit target"):
        RetargetSettings(fit_target="tight")


def test_layer_problem_adds_the_inner_source_garment_to_the_source_avatar(toy_result: tuple) -> None:
    """The outer garment's source gaps are measured to the cloth under it on the source, as its gaps on the
    target are measured to the retargeted inner garment."""
    p, inner, _ = toy_result
    plain = layer_problem(p, inner.garment_vertices, inner.garment_faces)
    assert torch.equal(plain.source_avatar_vertices, p.source_avatar_vertices)
    lp = layer_problem(p, inner.garment_vertices, inner.garment_faces,
                       inner_source=(p.garment_vertices, p.garment_faces))
    a = p.source_avatar_vertices.shape[0]
    assert torch.equal(lp.source_avatar_vertices, torch.cat([p.source_avatar_vertices, p.garment_vertices]))
    assert torch.equal(lp.source_avatar_faces[-p.garment_faces.shape[0]:], p.garment_faces + a)


def test_multilayer_second_garment_over_first(toy_result: tuple) -> None:
    p, inner, _ = toy_result
    c = toy_case(target_scale=1.3, target_offset=(2.0, -1.0, 0.5))
    from torchgarment.retarget.avatars import tube_mesh

    ov, of = tube_mesh(0.34, 0.34, -0.1, 1.15, 24, 9)
    p2 = problem_from_arrays(
        ov,
        of,
        c.source_skeleton,
        c.target_vertices,
        c.target_faces,
        c.target_skeleton,
        source_avatar=(c.source_vertices, c.source_faces),
    )
    lp = layer_problem(p2, inner.garment_vertices, inner.garment_faces)
    assert lp.avatar_vertices.shape[0] == p2.avatar_vertices.shape[0] + inner.garment_vertices.shape[0]
    outer = retarget(lp, progress=False)
    assert outer.metrics["intersections"] == 0
    # independent check: outer vs (avatar + inner garment) and outer alone
    av = torch.cat([c.target_vertices, inner.garment_vertices])
    af = torch.cat([c.target_faces, inner.garment_faces + c.target_vertices.shape[0]])
    inter_av, inter_self, dmin = _ipctk_checks(outer.garment_vertices, outer.garment_faces, av, af)
    assert not inter_av and not inter_self and dmin > 0


def test_check_result_detects_intersection() -> None:
    c = toy_case()
    # a garment pushed through the avatar's side
    x = c.garment_vertices.clone()
    x[:, 0] *= 1.6
    chk = check_result(x, c.garment_faces, c.target_vertices, c.target_faces, 0.002)
    assert chk["intersects_avatar"] and chk["intersections"] >= 1


def test_settings_validation() -> None:
    with pytest.raises(InputError):
        RetargetSettings(w_fit=-1.0)
    with pytest.raises(InputError, match="w_attach"):
        RetargetSettings(w_attach=-1.0)
    with pytest.raises(InputError, match="attach_distance"):
        RetargetSettings(attach_distance=0.0)
    with pytest.raises(InputError):
        RetargetSettings(step_bound="nope")
    with pytest.raises(InputError):
        RetargetSettings(broad_phase="Nope")


def test_moving_a_skeleton_joint_moves_the_hem() -> None:
    """Paper Fig. 9: the positional term keeps boundary loops at their coordinate along the nearest bone, so
    lowering the target's hip joint lowers the hem (the loop nearest to it) while the collar stays."""
    from torchgarment.body.skeleton import Skeleton

    def run(hip_drop: float) -> RetargetResult:
        c = toy_case()
        tj = c.target_skeleton.joints.clone()
        tj[0, 1] -= hip_drop
        target = Skeleton(tj, c.target_skeleton.bones.clone(), list(c.target_skeleton.names))
        p = problem_from_arrays(
            c.garment_vertices,
            c.garment_faces,
            c.source_skeleton,
            c.target_vertices,
            c.target_faces,
            target,
            source_avatar=(c.source_vertices, c.source_faces),
        )
        r = retarget(p, progress=False)
        assert r.metrics["intersections"] == 0
        y = r.garment_vertices[:, 1]
        y0 = c.garment_vertices[:, 1]
        hem = y0 < float(y0.min()) + 1e-6
        collar = y0 > float(y0.max()) - 1e-6
        return float(y[hem].mean()), float(y[collar].mean())

    hem_a, collar_a = run(0.0)
    hem_b, collar_b = run(0.15)
    assert hem_b < hem_a - 0.05, f"hem moved {1e3 * (hem_b - hem_a):.0f} mm for a 150 mm joint drop"
    assert abs(collar_b - collar_a) < 0.5 * abs(hem_b - hem_a)


def test_runs_are_reproducible_and_threads_are_restored(toy_result: tuple) -> None:
    """With one thread (the default) ipctk's queries run serially and a second run gives the same garment bit
    for bit (with two, runs of one pair differed by 0.4 mm); the caller's thread counts are restored."""
    import ipctk

    p, first, _ = toy_result
    torch_threads, ipctk_threads = torch.get_num_threads(), ipctk.get_num_threads()
    again = retarget(p, progress=False)
    assert torch.equal(again.garment_vertices, first.garment_vertices)
    assert torch.get_num_threads() == torch_threads and ipctk.get_num_threads() == ipctk_threads


def test_sparse_backend_auto_is_cholmod_when_cvxopt_is_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    """RetargetSettings' default "auto" resolves to the fastest installed SPD backend (CHOLMOD through cvxopt,
    else SuperLU) and the settings hold the resolved one; a named backend is kept."""
    import importlib
    import importlib.util

    from torchgarment.linalg import SparseBackend

    expected = SparseBackend.CHOLMOD if importlib.util.find_spec("cvxopt") else SparseBackend.SUPERLU
    assert SparseBackend.fastest_spd() is expected and RetargetSettings().sparse_backend is expected
    assert RetargetSettings(sparse_backend="superlu").sparse_backend is SparseBackend.SUPERLU
    real = importlib.util.find_spec

    def without_cvxopt(name: str, package: str | None = None) -> object:
        return None if name.startswith("cvxopt") else real(name, package)

    monkeypatch.setattr(importlib.util, "find_spec", without_cvxopt)
    assert SparseBackend.fastest_spd() is SparseBackend.SUPERLU
    assert RetargetSettings(sparse_backend="AUTO").sparse_backend is SparseBackend.SUPERLU
