"""Batch manifests: a YAML or JSON file of jobs (listed, or as cross products), validated up front.

A manifest is a mapping with ``jobs`` (a list of job entries) and/or ``cross`` (a list of cross-product
entries)::

    jobs:
      - {method: drape, garment: straight_skirt, size: "6", settings: {edge_length: 0.05}}
      - {method: drape, pattern: path/pattern.json, body: path/body.obj}
    cross:
      - {method: drape, garments: [straight_skirt, tshirt], sizes: ["6", "12"], settings: {edge_length: 0.05}}

A **job entry** has a ``method`` (:data:`METHODS`), the inputs the method names (``garment``, ``pattern``,
``size``, ``body``, ``model``; which ones each method takes is in :data:`METHODS`), an optional ``name`` and
``settings``: the single command's option names, underscored (``edge_length: 0.05`` is ``--edge-length
0.05``; ``true`` for a flag; a list for an option of several values). A ``pca_fit`` job without ``model``
takes ``garment`` or ``pattern`` and ``build`` (the ``pca build`` options, e.g. ``{bodies: 30}``): the model
is built once per distinct garment and build settings and shared by every fit that names it.

A **cross entry** has the same keys, where any input may be given in the plural (``garments``, ``patterns``,
``sizes``, ``bodies``, ``models``) as a list; the entry stands for every combination. A list item may also
be a mapping, whose keys are merged into the job (e.g. ``bodies: [{body: a.obj, settings: {target_skeleton:
a_skel.obj}}]`` for avatars that come with their own skeleton).

Relative paths are relative to the manifest's folder. Every entry is checked before anything runs (the
method, the keys, every setting against the command's own parser), and every bad entry is reported, one line
each (:class:`ManifestError`).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import itertools
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchgarment.batch.worker import LOGS, MODEL
from torchgarment.errors import InputError

__all__ = ["METHODS", "Job", "ManifestError", "Method", "load_manifest", "parse_manifest"]


class ManifestError(InputError):
    """A manifest with bad entries; the message has one line per bad entry."""


@dataclass(frozen=True)
class Method:
    """How a batch method maps onto its single command.

    Attributes:
        command: the subcommand words (``["pca", "fit"]``).
        inputs: manifest input key -> the command's option (``{"body": "--target-body"}``).
        path_settings: the settings whose values are file paths (resolved against the manifest's folder).
        render: the job's picture for the contact sheet, first existing name wins.
    """

    command: tuple[str, ...]
    inputs: dict[str, str]
    path_settings: frozenset[str] = frozenset()
    render: tuple[str, ...] = ()


METHODS: dict[str, Method] = {
    "drape": Method(("drape",), {"garment": "--pattern", "pattern": "--pattern", "size": "--size",
                                 "body": "--body"}, render=("drape.png",)),
    "adjust": Method(("adjust",), {"garment": "--garment", "pattern": "--pattern", "size": "--target-size",
                                   "body": "--target-body"},
                     path_settings=frozenset({"base_body"}), render=("overlay.png", "garment_target.png")),
    "grade": Method(("grade",), {"garment": "--garment", "pattern": "--pattern", "size": "--base-size",
                                 "body": "--base-body"}, path_settings=frozenset({"target_body"}),
                    render=("grade_nest.png",)),
    "retarget": Method(("retarget",), {"garment": "--garment", "body": "--target-avatar"},
                       path_settings=frozenset({"source_skeleton", "target_skeleton", "source_avatar",
                                                "skin_weights", "no_fit", "curves"}),
                       render=("retarget.png",)),
    "pca_fit": Method(("pca", "fit"), {"model": "--model", "body": "--body"}),  # `pca fit` writes no picture
}
"""The batch methods: ``drape``, ``adjust``, ``grade``, ``retarget`` and ``pca_fit`` (``torchgarment pca
fit``)."""

_INPUTS = ("garment", "pattern", "size", "body", "model")
_PLURAL = {"garments": "garment", "patterns": "pattern", "sizes": "size", "bodies": "body", "models": "model"}
_PATH_INPUTS = {"garment", "pattern", "body", "model"}
"""Inputs resolved against the manifest's folder when they look like paths (a library garment's name or a
chart size has no slash and no suffix and is kept as it is; a retarget garment is a file)."""
_ENTRY_KEYS = {"method", "name", "settings", "build", *_INPUTS}
_RESERVED = {"out", "resume", "no_progress", "log_dir", "help"}
"""Settings the batch runner sets itself (``--out`` is the job's folder, progress goes to the batch's bar)."""
_BUILD_RESERVED = _RESERVED | {"garment", "pattern", "cache"}


@dataclass(frozen=True)
class Job:
    """One job of a batch.

    Attributes:
        id: the job's folder name under ``DIR/jobs``: a readable slug and a hash of everything the job depends
            on, so that a changed job is a new job (``drape-straight_skirt-6-3f2a9c1e``).
        method: a :data:`METHODS` key.
        argv: the single command's arguments without ``--out`` (``["drape", "--pattern", ...]``).
        garment: what the garment column shows (library name or pattern file stem).
        body: what the body column shows (chart size or body file stem).
        bodies: the bodies the job loads, with the SDF voxel size it drapes them with (None: no SDF), for the
            shared preparation (each body fitted and its SDF built once per batch).
        build: for a ``pca_fit`` job without a model, the ``pca build`` arguments without ``--out``; else
            None.
        entry: where the job comes from in the manifest (``jobs[2]``, ``cross[0] #5``), for messages.
    """

    id: str
    method: str
    argv: tuple[str, ...]
    garment: str
    body: str
    bodies: tuple[tuple[str, float | None], ...] = ()
    build: tuple[str, ...] | None = None
    entry: str = ""

    @property
    def build_id(self) -> str | None:
        """Folder name of the shared PCA model under ``DIR/shared/pca`` (None without a build)."""
        if self.build is None:
            return None
        return "model-" + hashlib.sha256(json.dumps(self.build).encode()).hexdigest()[:10]


def load_manifest(path: str | Path) -> list[Job]:
    """Read and check a manifest file (``.yaml``/``.yml`` or ``.json``).

    Returns:
        The jobs, in manifest order (listed jobs first, then each cross product), duplicates removed.

    Raises:
        InputError: the file is missing or not YAML/JSON. ManifestError: bad entries (one line each).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"manifest {path}: no such file")
    text = path.read_text(encoding="utf-8", errors="replace")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as exc:  # yaml.YAMLError, json.JSONDecodeError
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"manifest {path}: not valid {'JSON' if path.suffix == '.json' else 'YAML'}: "
                         f"{first}") from None
    return parse_manifest(data, base_dir=path.resolve().parent, name=str(path))


def parse_manifest(data: Any, base_dir: Path, name: str = "manifest") -> list[Job]:
    """Check a decoded manifest and expand it into jobs (see the module docstring for the format).

    Args:
        data: the decoded YAML/JSON. base_dir: folder that relative paths are relative to. name: for
            messages.

    Raises:
        ManifestError: every bad entry, one line each.
    """
    if not isinstance(data, dict) or not ({"jobs", "cross"} & set(data)):
        raise ManifestError(f"{name}: expected a mapping with 'jobs' (a list of jobs) and/or 'cross' (a list "
                            "of cross products)")
    errors: list[str] = []
    unknown = sorted(set(data) - {"jobs", "cross"})
    if unknown:
        errors.append(f"{name}: unknown top-level key(s) {unknown}: only 'jobs' and 'cross'")
    entries: list[tuple[str, dict]] = []
    for section in ("jobs", "cross"):
        items = data.get(section) or []
        if not isinstance(items, list):
            errors.append(f"{name}: '{section}' must be a list")
            continue
        for i, item in enumerate(items):
            where = f"{section}[{i}]"
            if not isinstance(item, dict):
                errors.append(f"{name} {where}: expected a mapping, got {type(item).__name__}")
                continue
            if section == "jobs":
                entries.append((where, item))
            else:
                try:
                    entries.extend((f"{where} #{n}", job) for n, job in enumerate(_expand_cross(item)))
                except ManifestError as exc:
                    errors.append(f"{name} {where}: {exc}")
    parser = _command_parser()
    jobs: list[Job] = []
    seen: set[str] = set()
    for where, entry in entries:
        try:
            job = _make_job(entry, base_dir, parser, where)
        except ManifestError as exc:
            errors.append(f"{name} {where}: {exc}")
            continue
        if job.id not in seen:
            seen.add(job.id)
            jobs.append(job)
    if errors:
        raise ManifestError("\n".join(errors))
    if not jobs:
        raise ManifestError(f"{name}: no jobs")
    return jobs


def _expand_cross(item: dict) -> list[dict]:
    axes: list[list[dict]] = []
    base = {k: v for k, v in item.items() if k not in _PLURAL}
    for plural, single in _PLURAL.items():
        if plural not in item:
            continue
        if single in item:
            raise ManifestError(f"give '{single}' or '{plural}', not both")
        values = item[plural]
        if not isinstance(values, list) or not values:
            raise ManifestError(f"'{plural}' must be a non-empty list")
        axes.append([dict(v) if isinstance(v, dict) else {single: v} for v in values])
    if not axes:
        raise ManifestError(f"a cross entry needs at least one list ({', '.join(_PLURAL)})")
    jobs = []
    for combo in itertools.product(*axes):
        job = dict(base)
        settings = dict(base.get("settings") or {}) if isinstance(base.get("settings"), dict) else None
        for part in combo:
            for key, value in part.items():
                if key == "settings" and isinstance(value, dict) and settings is not None:
                    settings.update(value)
                else:
                    job[key] = value
        if settings is not None:
            job["settings"] = settings
        jobs.append(job)
    return jobs


def _command_parser() -> argparse.ArgumentParser:
    from torchgarment.cli import build_parser

    return build_parser()


def _subparser(parser: argparse.ArgumentParser, words: tuple[str, ...]) -> argparse.ArgumentParser:
    for word in words:
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = action.choices[word]
    return parser


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """dest -> action of the parser's ``--long`` options."""
    return {a.dest: a for a in parser._actions if any(o.startswith("--") for o in a.option_strings)}


def _scalar_text(value: Any, what: str) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ManifestError(f"{what}: expected a string or a number, got {value!r}")
    return str(value)


def _resolve(value: str, base_dir: Path) -> str:
    """A path relative to the manifest's folder made absolute; a library name or chart size kept."""
    p = Path(value).expanduser()
    if p.is_absolute():
        return str(p)
    if (base_dir / p).exists() or "/" in value or p.suffix:
        return str((base_dir / p).resolve())
    return value


def _settings_argv(settings: dict, options: dict[str, argparse.Action], reserved: set[str],
                   paths: frozenset[str], base_dir: Path, what: str) -> list[str]:
    argv: list[str] = []
    for key, value in settings.items():
        if not isinstance(key, str) or key in reserved:
            raise ManifestError(f"{what} '{key}' is set by the batch runner, not by a manifest")
        if key not in options:
            known = ", ".join(sorted(k for k in options if k not in reserved))
            raise ManifestError(f"{what} '{key}' is not an option of this command (options: {known})")
        action = options[key]
        flag = max(action.option_strings, key=len)
        if isinstance(action, argparse._StoreTrueAction):
            if not isinstance(value, bool):
                raise ManifestError(f"{what} '{key}' is a flag: give true or false, got {value!r}")
            argv += [flag] if value else []
            continue
        values = value if isinstance(value, list) else [value]
        if isinstance(value, list) and action.nargs not in ("+", "*"):
            raise ManifestError(f"{what} '{key}' takes one value, got a list")
        texts = [_scalar_text(v, f"{what} '{key}'") for v in values]
        if key in paths:
            texts = [_resolve(t, base_dir) for t in texts]
        argv += [flag, *texts]
    return argv


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """Parse with the command's own parser; its error line becomes a ManifestError."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args(argv)
    except SystemExit:
        lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
        message = lines[-1] if lines else "invalid options"
        raise ManifestError(re.sub(r"^torchgarment(?: \w+)*: error: ", "", message)) from None


def _label(value: str, base_dir: Path) -> str:
    """A short name of an input for the summary: a library name or chart size as it is, a file as its path
    relative to the manifest's folder without the suffix (``customers/ann``), or its stem."""
    if not ("/" in value or "." in value):
        return value
    p = Path(value)
    try:
        return str(p.relative_to(base_dir).with_suffix(""))
    except ValueError:
        return p.stem


def _slug(*parts: str) -> str:
    text = "-".join(p for p in parts if p).replace("->", "-to-")
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")[:80]


def _make_job(entry: dict, base_dir: Path, parser: argparse.ArgumentParser, where: str) -> Job:
    unknown = sorted(set(entry) - _ENTRY_KEYS)
    if unknown:
        raise ManifestError(f"unknown key(s) {unknown} (keys: {', '.join(sorted(_ENTRY_KEYS))}; in a cross "
                            f"entry also {', '.join(_PLURAL)})")
    method_name = entry.get("method")
    if method_name not in METHODS:
        raise ManifestError(f"method {method_name!r} is not one of {', '.join(METHODS)}")
    method = METHODS[method_name]
    settings = entry.get("settings") or {}
    if not isinstance(settings, dict):
        raise ManifestError("'settings' must be a mapping of option name -> value")
    inputs = {k: _scalar_text(entry[k], f"'{k}'") for k in _INPUTS if k in entry}
    for key in inputs:
        if key not in method.inputs and not (method_name == "pca_fit" and key in ("garment", "pattern")):
            raise ManifestError(f"method {method_name} takes no '{key}' (it takes "
                                f"{', '.join(method.inputs)})")
    for key in _PATH_INPUTS & set(inputs):
        inputs[key] = _resolve(inputs[key], base_dir)
    if method_name == "drape" and "garment" in inputs and "body" not in inputs and "size" in inputs:
        inputs["body"] = inputs["size"]  # a library garment drafted for a chart size, draped on that size
    if method_name == "drape" and "garment" in inputs and "pattern" in inputs:
        raise ManifestError("give 'garment' or 'pattern', not both")
    sub = _subparser(parser, method.command)
    options = _options(sub)
    argv = list(method.command)
    build = None
    if method_name == "pca_fit" and "model" not in inputs:
        build = _build_argv(entry, inputs, parser, base_dir)
        argv += ["--model", MODEL]  # the shared model's folder, set where the job runs
    elif entry.get("build") is not None:
        raise ManifestError("'build' is for a pca_fit job without a model")
    for key, flag in method.inputs.items():
        if key in inputs:
            argv += [flag, inputs[key]]
    argv += _settings_argv(settings, options, _RESERVED | {o.lstrip("-").replace("-", "_") for o in
                                                           method.inputs.values()},
                           method.path_settings, base_dir, "setting")
    args = _parse(parser, [*argv, "--out", "OUT"])  # the command's own checks (types, choices, required)
    if "no_progress" in options:
        argv.append("--no-progress")
    if "log_dir" in options:
        argv += ["--log-dir", LOGS]  # TensorBoard scalars into the job's own folder
    garment = inputs.get("garment") or _label(inputs.get("pattern", "") or inputs.get("model", ""), base_dir)
    body = _body_label(method_name, inputs, args, base_dir)
    ident = hashlib.sha256(json.dumps([argv, build]).encode()).hexdigest()[:8]
    name = entry.get("name")
    if name is not None and not isinstance(name, str):
        raise ManifestError("'name' must be a string")
    slug = _slug(method_name, garment, body) if name is None else _slug(name)
    return Job(id=f"{slug}-{ident}", method=method_name, argv=tuple(argv), garment=garment, body=body,
               bodies=_job_bodies(method_name, args), build=build, entry=where)


def _body_label(method: str, inputs: dict, args: argparse.Namespace, base_dir: Path) -> str:
    if method == "grade":
        base = inputs.get("size") or _label(inputs.get("body", ""), base_dir)
        targets = args.sizes or [_label(t, base_dir) for t in args.target_body or []]
        return f"{base}->{'+'.join(targets)}"
    if method == "adjust":
        base = args.base_size or _label(args.base_body or "", base_dir)
        return f"{base}->{inputs.get('size') or _label(inputs.get('body', ''), base_dir)}"
    return inputs.get("size") if "body" not in inputs else _label(inputs["body"], base_dir)


def _job_bodies(method: str, args: argparse.Namespace) -> tuple[tuple[str, float | None], ...]:
    if method == "drape":
        return ((args.body, args.voxel),)
    if method in ("adjust", "grade"):
        base = args.base_size or args.base_body
        targets = ([args.target_size or args.target_body] if method == "adjust"
                   else (args.sizes or args.target_body or []))
        return tuple((b, args.voxel) for b in [base, *targets])
    return ()


def _build_argv(entry: dict, inputs: dict, parser: argparse.ArgumentParser,
                base_dir: Path) -> tuple[str, ...]:
    source = [k for k in ("garment", "pattern") if k in inputs]
    if len(source) != 1:
        raise ManifestError("a pca_fit job takes 'model' (a built model folder), or 'garment' or 'pattern' "
                            "with 'build' (the pca build options) to build the model once for every fit")
    build = entry.get("build") or {}
    if not isinstance(build, dict):
        raise ManifestError("'build' must be a mapping of `pca build` option name -> value")
    sub = _subparser(parser, ("pca", "build"))
    argv = ["pca", "build", f"--{source[0]}", inputs[source[0]]]
    argv += _settings_argv(build, _options(sub), _BUILD_RESERVED, frozenset({"dataset"}), base_dir,
                           "build option")
    _parse(parser, [*argv, "--out", "OUT"])
    return (*argv, "--no-progress")
