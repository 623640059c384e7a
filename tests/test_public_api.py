"""Every name a subpackage re-exports imports from it, is the object of its defining module, and is documented
in the package docstring."""

from __future__ import annotations

import importlib
import inspect

import pytest

PUBLIC = {
    "torchgarment.adjust": [
        "adjust",
        "prepare",
        "optimize",
        "pattern_from_mesh",
        "AdjustSettings",
        "AdjustResult",
        "AdjustSetup",
        "AdjustObjective",
        "CostWeights",
        "DistanceCost",
        "SmoothnessCost",
        "StretchingCost",
        "PositionalCost",
        "FixingRegularizer",
        "BoundaryCurvatureRegularizer",
        "SeamLengthRegularizer",
        "BoundaryParametrization",
        "transfer_deformation",
        "make_optimizer",
        "OptimizerKind",
        "PreconditionedGD",
        "LBFGS",
        "GaussNewton",
        "FixedPoint",
        "AdjustProblem",
        "grade",
        "GradeResult",
        "base_drape_settings",
        "measure_fit",
        "FitScale",
        "LineFit",
        "fit_rows",
        "construction_lines",
    ],
    "torchgarment.retarget": [
        "FitTarget",
        "retarget",
        "retarget_layers",
        "layer_problem",
        "check_result",
        "RetargetSettings",
        "RetargetResult",
        "RetargetError",
        "RetargetProblem",
        "Similarity",
        "problem_from_arrays",
        "problem_from_bodies",
        "load_problem",
        "shrink_avatar",
        "ShrunkAvatar",
        "list_avatars",
        "make_avatar",
        "TestAvatar",
        "edit_by_bones",
        "toy_case",
        "ToyCase",
    ],
    "torchgarment.sim": [
        "drape",
        "SupportLoop",
        "DrapeSettings",
        "DrapeResult",
        "DrapeStage",
        "seam_gaps",
        "max_seam_gap",
        "vertex_stretch_ratio",
        "Scene",
        "SimModel",
        "Effect",
        "Material",
        "solve",
        "SolveSettings",
        "SolveInfo",
        "SolverKind",
        "Preconditioner",
        "DifferentiableSolver",
        "QuasistaticSolve",
        "BackwardMode",
        "AdjointHessian",
        "AdjointLinearSolver",
        "NonConvergenceError",
        "NonConvergenceWarning",
        "EnergyTerm",
        "HessianBlocks",
        "PlanarSprings",
        "SewingSprings",
        "QuadraticBending",
        "Gravity",
        "Pins",
        "BodyBarrier",
        "SelfContact",
        "BodyMeshContact",
    ],
    "torchgarment.datadriven": [
        "BodyDataset",
        "BodyPCA",
        "build_basis",
        "BasisSettings",
        "BasisFit",
        "Interpolation",
        "ClothingBasis",
        "BodyFrame",
        "place_for_body",
        "drape_on_body",
        "basis_cache_dir",
        "OnlineFitter",
        "push_out",
        "PushOutResult",
        "refine",
    ],
    "torchgarment.body": ["Body", "BodyMeasurements", "Skeleton", "measure_body", "chart_row", "list_sizes"],
    "torchgarment.pattern": [
        "SewingPattern",
        "Panel",
        "Edge",
        "EdgeKind",
        "EdgeRef",
        "Notch",
        "Stitch",
        "StitchOrientation",
        "DraftMeasurements",
        "draft",
        "list_garments",
        "load_pattern",
        "save_pattern",
        "mesh_pattern",
    ],
    "torchgarment.sdf": [
        "BodySDF",
        "MeshProximity",
        "SDFSampling",
        "SDFSettings",
        "SDFGridData",
        "SignType",
        "build_sdf_grid",
        "cached_sdf",
        "closest_points_on_triangles",
        "exact_signed_distance",
        "sdf_cache_dir",
        "sdf_cache_key",
        "sdf_cache_path",
        "winding_number",
    ],
    "torchgarment.render": [
        "render_views",
        "render_image",
        "MeshLayer",
        "View",
        "OrthoCamera",
        "FigureLayout",
        "RenderStyle",
        "ScalarColors",
        "ScalarLocation",
        "Fragments",
        "rasterize",
        "fit_camera",
        "contact_sheet",
        "DEFAULT_COLOR",
    ],
    "torchgarment.batch": [
        "METHODS",
        "BatchReport",
        "BatchSettings",
        "Job",
        "ManifestError",
        "Method",
        "load_manifest",
        "parse_manifest",
        "prepare_body",
        "run_batch",
        "run_command",
        "run_pca_fits",
    ],
    "torchgarment.structures": [
        "GarmentMesh",
        "MeshLayout",
        "check_mesh",
        "edge_table",
        "face_areas",
        "find_boundary_edges",
        "find_degenerate_faces",
        "find_misoriented_edges",
        "find_nonmanifold_edges",
        "find_unreferenced_vertices",
        "seam_weld_index",
        "weld_vertices",
        "welded_faces",
    ],
    "torchgarment.io": ["atomic_open", "atomic_path"],
    "torchgarment": ["InputError", "MeshError", "PatternError", "TorchGarmentError"],
}


@pytest.mark.parametrize("package", sorted(PUBLIC))
def test_reexports(package: str) -> None:
    mod = importlib.import_module(package)
    names = PUBLIC[package]
    assert sorted(mod.__all__) == sorted(n for n in mod.__all__ if n in names or n == "__version__")
    assert set(names) <= set(mod.__all__), sorted(set(names) - set(mod.__all__))
    for name in names:
        obj = getattr(mod, name)
        exec(f"from {package} import {name}", {})  # noqa: S102 - the statement users write
        if inspect.isclass(obj) or inspect.isfunction(obj):
            home = importlib.import_module(obj.__module__)
            assert getattr(home, obj.__name__) is obj, (
                f"{package}.{name} is not {obj.__module__}.{obj.__name__}"
            )
            # errors live in torchgarment.errors (the bottom layer) and are re-exported where they are raised
            assert obj.__module__.startswith(package) or obj.__module__ == "torchgarment.errors", (
                f"{package}.{name} comes from {obj.__module__}"
            )


@pytest.mark.parametrize(
    "package",
    [
        "torchgarment.adjust",
        "torchgarment.retarget",
        "torchgarment.sim",
        "torchgarment.datadriven",
        "torchgarment.batch",
        "torchgarment.structures",
        "torchgarment.body",
        "torchgarment.io",
    ],
)
def test_package_docstring_names_every_reexport(package: str) -> None:
    mod = importlib.import_module(package)
    missing = [n for n in mod.__all__ if f"`{n}`" not in mod.__doc__ and f"``{n}" not in mod.__doc__]
    assert not missing, f"{package} docstring does not mention {missing}"


def test_drape_is_the_function_after_its_module_is_imported() -> None:
    import torchgarment.sim.drape  # noqa: F401 - the submodule shares the function's name
    from torchgarment.sim import drape

    assert inspect.isfunction(drape)
