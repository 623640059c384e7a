"""Batch fitting at catalogue scale on Ray: many drape, adjust, grade, retarget and PCA-fit jobs in one call,
locally (Ray embedded) or on a Ray cluster.

Re-exported here:

* manifests (:mod:`torchgarment.batch.manifest`): :func:`load_manifest` and :func:`parse_manifest` turn a YAML
  or JSON manifest into :class:`Job` s (checked up front, :class:`ManifestError` with one line per bad entry);
  :data:`METHODS` with their :class:`Method` mapping onto the single commands;
* the runner (:mod:`torchgarment.batch.runner`): :func:`run_batch` with :class:`BatchSettings` returns a
  :class:`BatchReport`;
* what workers run (:mod:`torchgarment.batch.worker`): :func:`run_command` (one job: the single command,
  in-process), :func:`run_pca_fits` (many ``pca_fit`` jobs on one model in one batched call) and
  :func:`prepare_body` (a body and its SDF, once per batch).

Ray is an optional dependency (``pip install -e ".[batch]"``); it is imported only when a batch runs. The
command line is ``torchgarment batch`` (:mod:`torchgarment.batch.cli`).
"""

from torchgarment.batch.manifest import METHODS, Job, ManifestError, Method, load_manifest, parse_manifest
from torchgarment.batch.runner import BatchReport, BatchSettings, run_batch
from torchgarment.batch.worker import prepare_body, run_command, run_pca_fits

__all__ = [
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
]
