"""Forward kinematics of a skeleton through pytorch-kinematics.

A :class:`~torchgarment.body.skeleton.Skeleton` is turned into a URDF robot: one link per joint and, for
every joint, three revolute (URDF ``continuous``) joints about the world x, y and z axes, so a joint's local
rotation is ``R = Rx(a) @ Ry(b) @ Rz(c)`` (intrinsic XYZ Euler angles). The rest pose is the skeleton's
joint positions with every joint frame aligned with the world axes. Forests are joined under a virtual
``world`` link. The chain is loaded with ``pytorch_kinematics.build_chain_from_urdf``; its static offsets
are then set from the float64 joint positions (the URDF parser rounds them to float32). Parsing is slow
(about 1 s for 100 joints), so the parsed chain is cached per topology (the parent of every joint; the last
8 topologies): a skeleton with known bones copies it and only sets its own offsets.

Conventions (the SMPL ones):

* ``rotations[j]`` rotates everything below joint ``j`` (the bones leaving ``j`` and their subtrees) about
  joint ``j``, expressed in the parent's frame.
* World transform of joint ``j``: ``G_j = G_parent(j) @ [[R_j, t_j - t_parent(j)], [0, 1]]``; for a root,
  ``G_r = [[R_r, t_r], [0, 1]]``. ``G_j[:3, 3]`` is the posed joint position.
* Skinning transform: ``A_j = G_j @ [[I, -t_j], [0, 1]]`` maps rest-pose points to posed points.

Bone direction: ``bones`` rows are (parent, child). If they do not form a parent->child forest as written
(a joint with two parents), but the undirected bone graph is still acyclic, each connected component is
re-rooted at its joint nearest to the component's mean joint position (the pelvis or spine of a humanoid)
and bones are directed away from it. A bone graph with a cycle is rejected.
"""

from __future__ import annotations

import copy
import enum
from collections import OrderedDict, deque
from typing import TYPE_CHECKING

import torch

from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

if TYPE_CHECKING:
    import pytorch_kinematics as pk

__all__ = [
    "KinematicSkeleton",
    "RotationFormat",
    "axis_angle_to_matrix",
    "check_bone_forest",
    "euler_xyz_to_matrix",
    "joint_parents",
    "matrix_to_euler_xyz",
    "skeleton_to_urdf",
]


class RotationFormat(enum.Enum):
    """How per-joint rotations are given to :meth:`KinematicSkeleton.forward_kinematics`."""

    AXIS_ANGLE = "axis_angle"  # (..., J, 3) rotation vectors, radians
    MATRIX = "matrix"  # (..., J, 3, 3) rotation matrices


# ----------------------------------------------------------------------------------------------------------
# Bone graph
# ----------------------------------------------------------------------------------------------------------


def check_bone_forest(num_joints: int, bones: torch.Tensor) -> None:
    """Check that bones index valid joints and that the undirected bone graph has no cycle.

    Args:
        num_joints: J.
        bones: (B, 2) integer joint index pairs.

    Raises:
        InputError: wrong shape, index out of range, a bone from a joint to itself, a repeated bone or a
            cycle.
    """
    if not isinstance(bones, torch.Tensor) or bones.ndim != 2 or bones.shape[1] != 2:
        shape = tuple(bones.shape) if isinstance(bones, torch.Tensor) else type(bones).__name__
        raise InputError(f"bones must be a (B, 2) tensor of joint indices, got {shape}")
    if bones.is_floating_point():
        raise InputError(f"bones must be integer joint indices, got {bones.dtype}")
    pairs = bones.detach().cpu().long().tolist()
    parent = list(range(num_joints))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for k, (a, b) in enumerate(pairs):
        if not (0 <= a < num_joints and 0 <= b < num_joints):
            raise InputError(f"bone {k} ({a}, {b}) indexes a joint outside [0, {num_joints})")
        if a == b:
            raise InputError(f"bone {k} connects joint {a} to itself")
        ra, rb = find(a), find(b)
        if ra == rb:
            raise InputError(
                f"bone graph has a cycle: bone {k} ({a}, {b}) closes a loop (bones must form a forest)"
            )
        parent[ra] = rb


def joint_parents(skeleton: Skeleton) -> torch.Tensor:
    """Parent joint of every joint, orienting the bones as described in the module docstring.

    Args:
        skeleton: joints (J, 3) and bones (B, 2).

    Returns:
        (J,) long CPU tensor, the parent index of each joint, -1 for roots.

    Raises:
        InputError: the bone graph is not a forest.
    """
    num_joints = skeleton.num_joints
    if skeleton.joints.ndim != 2 or skeleton.joints.shape[1] != 3 or num_joints == 0:
        raise InputError("skeleton joints must have shape (J, 3) with J > 0, got "
                         f"{tuple(skeleton.joints.shape)}")
    if not torch.isfinite(skeleton.joints).all():
        raise InputError("skeleton joints must be finite")
    check_bone_forest(num_joints, skeleton.bones)
    pairs = skeleton.bones.detach().cpu().long()
    parents = torch.full((num_joints,), -1, dtype=torch.long)
    if pairs.shape[0] == 0:
        return parents
    if torch.bincount(pairs[:, 1], minlength=num_joints).max() <= 1:
        parents[pairs[:, 1]] = pairs[:, 0]
        return parents
    # Re-root every component at the joint nearest to the component's mean joint position.
    adjacency: list[list[int]] = [[] for _ in range(num_joints)]
    for a, b in pairs.tolist():
        adjacency[a].append(b)
        adjacency[b].append(a)
    joints = skeleton.joints.detach().cpu().double()
    seen = [False] * num_joints
    for start in range(num_joints):
        if seen[start]:
            continue
        component, queue = [start], deque([start])
        seen[start] = True
        while queue:
            for n in adjacency[queue.popleft()]:
                if not seen[n]:
                    seen[n] = True
                    component.append(n)
                    queue.append(n)
        comp = torch.tensor(component)
        centre = joints[comp].mean(dim=0)
        root = int(comp[torch.argmin(torch.linalg.vector_norm(joints[comp] - centre, dim=1))])
        visited, queue = {root}, deque([root])
        while queue:
            j = queue.popleft()
            for n in adjacency[j]:
                if n not in visited:
                    visited.add(n)
                    parents[n] = j
                    queue.append(n)
    return parents


# ----------------------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------------------


def _skew(v: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, safe (finite values and gradients) at zero angle.

    Args:
        axis_angle: (..., 3) rotation vectors (axis times angle in radians).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    theta2 = (axis_angle * axis_angle).sum(dim=-1)
    small = theta2 < 1e-6
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """``Rx(a) @ Ry(b) @ Rz(c)`` for angles (..., 3) = (a, b, c) in radians; returns (..., 3, 3)."""
    eye = torch.eye(3, dtype=angles.dtype, device=angles.device)
    return (
        axis_angle_to_matrix(angles[..., 0, None] * eye[0])
        @ axis_angle_to_matrix(angles[..., 1, None] * eye[1])
        @ axis_angle_to_matrix(angles[..., 2, None] * eye[2])
    )


def matrix_to_euler_xyz(matrix: torch.Tensor) -> torch.Tensor:
    """Intrinsic XYZ Euler angles of rotation matrices: ``matrix = Rx(a) @ Ry(b) @ Rz(c)``.

    At gimbal lock (``|cos b|`` below the square root of the dtype's epsilon) ``c`` is set to 0 and ``a``
    takes the whole remaining rotation, so values stay exact there; gradients are finite everywhere but
    only meaningful away from the lock.

    Args:
        matrix: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) angles (a, b, c) in radians, with b in [-pi/2, pi/2].
    """
    r = matrix
    eps = torch.finfo(r.dtype).eps ** 0.5
    cb2 = r[..., 0, 0] ** 2 + r[..., 0, 1] ** 2
    lock = cb2 < eps * eps
    one, zero = torch.ones_like(cb2), torch.zeros_like(cb2)
    cb = torch.where(lock, zero, torch.sqrt(torch.where(lock, one, cb2)))
    b = torch.atan2(r[..., 0, 2], cb)
    a_free = torch.atan2(torch.where(lock, zero, -r[..., 1, 2]), torch.where(lock, one, r[..., 2, 2]))
    c_free = torch.atan2(torch.where(lock, zero, -r[..., 0, 1]), torch.where(lock, one, r[..., 0, 0]))
    a_lock = torch.atan2(torch.where(lock, r[..., 2, 1], zero), torch.where(lock, r[..., 1, 1], one))
    a = torch.where(lock, a_lock, a_free)
    c = torch.where(lock, zero, c_free)
    return torch.stack([a, b, c], dim=-1)


# ----------------------------------------------------------------------------------------------------------
# URDF and chain
# ----------------------------------------------------------------------------------------------------------


def _link(j: int) -> str:
    return f"joint{j}"


def _offsets(joints: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
    """(J, 3) float64 translation from each joint's parent (or the world origin) to the joint."""
    joints = joints.detach().cpu().double()
    parent_pos = torch.where((parents >= 0)[:, None], joints[parents.clamp(min=0)], torch.zeros_like(joints))
    return joints - parent_pos


def skeleton_to_urdf(skeleton: Skeleton, parents: torch.Tensor | None = None, name: str = "skeleton") -> str:
    """URDF text of a skeleton: link ``joint{j}`` per joint, three ``continuous`` joints per joint.

    Args:
        skeleton: joints (J, 3) in metres and bones.
        parents: (J,) parent indices (-1 for roots); computed with :func:`joint_parents` when None.
        name: robot name.

    Returns:
        The URDF document as a string; links ``world``, ``joint{j}``, ``joint{j}_x``, ``joint{j}_y``;
        joints ``joint{j}_rx``, ``joint{j}_ry``, ``joint{j}_rz``.
    """
    if parents is None:
        parents = joint_parents(skeleton)
    offsets = _offsets(skeleton.joints, parents).tolist()
    out = [f'<robot name="{name}">', '  <link name="world"/>']
    for j in range(skeleton.num_joints):
        out.append(f'  <link name="{_link(j)}_x"/><link name="{_link(j)}_y"/><link name="{_link(j)}"/>')
    for j, p in enumerate(parents.tolist()):
        parent_link = "world" if p < 0 else _link(j=p)
        x, y, z = offsets[j]
        chain = [(parent_link, f"{_link(j)}_x", "rx", "1 0 0", f"{x!r} {y!r} {z!r}"),
                 (f"{_link(j)}_x", f"{_link(j)}_y", "ry", "0 1 0", "0 0 0"),
                 (f"{_link(j)}_y", _link(j), "rz", "0 0 1", "0 0 0")]
        for parent, child, suffix, axis, xyz in chain:
            out.append(
                f'  <joint name="{_link(j)}_{suffix}" type="continuous"><parent link="{parent}"/>'
                f'<child link="{child}"/><origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="{axis}"/></joint>'
            )
    out.append("</robot>")
    return "\n".join(out)


#: Chains of recently used skeleton topologies (building one from its URDF costs about 1 s for 100 joints).
_CHAIN_TEMPLATES: "OrderedDict[tuple[int, ...], tuple[object, dict[str, int]]]" = OrderedDict()
_MAX_CHAIN_TEMPLATES = 8


def _chain_template(urdf: str, parents: tuple[int, ...]) -> tuple[pk.Chain, dict[str, int]]:
    """The float64 CPU pytorch-kinematics chain of a topology and its frame index map (cached per topology).

    Only the static offsets of the ``joint{j}_x`` frames depend on the joint positions; callers copy the
    template and overwrite them.
    """
    import pytorch_kinematics as pk

    if parents in _CHAIN_TEMPLATES:
        _CHAIN_TEMPLATES.move_to_end(parents)
        return _CHAIN_TEMPLATES[parents]
    try:
        urdf_chain = pk.build_chain_from_urdf(urdf)
    except Exception as e:  # pragma: no cover - the URDF is generated here
        raise InputError(f"pytorch-kinematics rejected the skeleton URDF: {type(e).__name__}: {e}") from None
    root = urdf_chain.find_frame("world")
    root.to(dtype=torch.float64, device="cpu")
    chain = pk.Chain(root, dtype=torch.float64, device="cpu")
    _CHAIN_TEMPLATES[parents] = (chain, dict(chain.frame_to_idx))
    while len(_CHAIN_TEMPLATES) > _MAX_CHAIN_TEMPLATES:
        _CHAIN_TEMPLATES.popitem(last=False)
    return _CHAIN_TEMPLATES[parents]


class KinematicSkeleton:
    """Forward kinematics of a skeleton, computed by a pytorch-kinematics chain built from its URDF.

    Differentiable w.r.t. the rotations (not w.r.t. the rest joint positions, which are constants of the
    chain). Works on any device and floating dtype: the chain is built once in float64 on the CPU and
    copied to the rotations' dtype and device on first use.

    Attributes:
        skeleton: the rest-pose skeleton.
        parents: (J,) long parent indices (-1 for roots), see :func:`joint_parents`.
        urdf: the URDF text loaded into the chain.
    """

    def __init__(self, skeleton: Skeleton) -> None:
        from pytorch_kinematics import transforms as tf

        self.skeleton = skeleton
        self.parents = joint_parents(skeleton)
        self.urdf = skeleton_to_urdf(skeleton, self.parents)
        template, frame_of = _chain_template(self.urdf, tuple(self.parents.tolist()))
        chain = copy.deepcopy(template)
        # Set the exact float64 joint offsets (the URDF parser rounds them to float32).
        offsets = _offsets(skeleton.joints, self.parents)
        x_frames = torch.tensor([frame_of[f"{_link(j)}_x"] for j in range(skeleton.num_joints)],
                                dtype=torch.long)
        chain._static_offsets[x_frames, :3, 3] = offsets
        for j in range(skeleton.num_joints):
            k = int(x_frames[j])
            chain.joint_offsets[k] = chain._static_offsets[k][None].clone()
            chain.find_frame(f"{_link(j)}_x").joint.offset = tf.Transform3d(pos=offsets[j],
                                                                            dtype=torch.float64)
        names = chain.get_joint_parameter_names()
        position = {n: i for i, n in enumerate(names)}
        dof = torch.tensor(
            [[position[f"{_link(j)}_{s}"] for s in ("rx", "ry", "rz")] for j in range(skeleton.num_joints)],
            dtype=torch.long,
        )
        self._gather = torch.argsort(dof.flatten())  # th[:, k] = angles.flatten()[:, gather[k]]
        self._frames = torch.tensor([frame_of[_link(j)] for j in range(skeleton.num_joints)])
        self._chains = {(torch.float64, torch.device("cpu")): chain}
        self._rest = skeleton.joints.detach().cpu().double()

    @property
    def num_joints(self) -> int:
        return self.skeleton.num_joints

    def chain(self, dtype: torch.dtype, device: torch.device | str) -> pk.Chain:
        """The pytorch-kinematics chain for ``dtype`` and ``device`` (built on first use)."""
        key = (dtype, torch.device(device))
        if key not in self._chains:
            base = self._chains[(torch.float64, torch.device("cpu"))]
            self._chains[key] = copy.deepcopy(base).to(dtype=dtype, device=key[1])
        return self._chains[key]

    def _euler(self, rotations: torch.Tensor, rotation_format: RotationFormat) -> tuple[torch.Tensor, bool]:
        fmt = RotationFormat(rotation_format)
        if not isinstance(rotations, torch.Tensor) or not rotations.is_floating_point():
            raise InputError("rotations must be a floating-point tensor")
        j = self.num_joints
        if fmt is RotationFormat.AXIS_ANGLE:
            if rotations.ndim not in (2, 3) or tuple(rotations.shape[-2:]) != (j, 3):
                raise InputError(
                    f"axis-angle rotations must have shape (J, 3) or (B, J, 3) with J={j}, "
                    f"got {tuple(rotations.shape)}"
                )
            matrices = axis_angle_to_matrix(rotations)
        else:
            if rotations.ndim not in (3, 4) or tuple(rotations.shape[-3:]) != (j, 3, 3):
                raise InputError(
                    f"rotation matrices must have shape (J, 3, 3) or (B, J, 3, 3) with J={j}, "
                    f"got {tuple(rotations.shape)}"
                )
            matrices = rotations
        batched = matrices.ndim == 4
        return matrix_to_euler_xyz(matrices.reshape(-1, j, 3, 3)), batched

    def forward_kinematics(
        self, rotations: torch.Tensor, *, rotation_format: RotationFormat = RotationFormat.AXIS_ANGLE
    ) -> torch.Tensor:
        """World transforms of every joint frame.

        Args:
            rotations: local rotations of every joint, (J, 3) / (B, J, 3) axis-angle in radians or
                (J, 3, 3) / (B, J, 3, 3) matrices, see :class:`RotationFormat`.
            rotation_format: how ``rotations`` is given.

        Returns:
            (J, 4, 4) or (B, J, 4, 4) transforms ``G_j`` (translation part in metres) in the dtype and on
            the device of ``rotations``.

        Raises:
            InputError: wrong shape or dtype.
        """
        angles, batched = self._euler(rotations, rotation_format)
        chain = self.chain(angles.dtype, angles.device)
        batch = angles.shape[0]
        th = angles.reshape(batch, -1)[:, self._gather.to(angles.device)]
        frames = chain.forward_kinematics_tensor(th)  # (num_frames, B, 4, 4)
        out = frames[self._frames.to(angles.device)].transpose(0, 1)
        return out if batched else out[0]

    def skinning_transforms(
        self, rotations: torch.Tensor, *, rotation_format: RotationFormat = RotationFormat.AXIS_ANGLE
    ) -> torch.Tensor:
        """Transforms ``A_j = G_j @ [[I, -t_j], [0, 1]]`` mapping rest-pose points to posed points.

        Args and shapes as :meth:`forward_kinematics`.
        """
        g = self.forward_kinematics(rotations, rotation_format=rotation_format)
        rest = self._rest.to(dtype=g.dtype, device=g.device)
        translation = g[..., :3, 3] - (g[..., :3, :3] @ rest[..., None])[..., 0]
        top = torch.cat([g[..., :3, :3], translation[..., None]], dim=-1)
        return torch.cat([top, g[..., 3:, :]], dim=-2)

    def posed_joints(
        self, rotations: torch.Tensor, *, rotation_format: RotationFormat = RotationFormat.AXIS_ANGLE
    ) -> torch.Tensor:
        """Posed joint positions (J, 3) or (B, J, 3) in metres."""
        return self.forward_kinematics(rotations, rotation_format=rotation_format)[..., :3, 3]
