"""Animation: quaternions, keyframed object transforms and camera trajectories over time.

Quaternions are ``(..., 4)`` tensors ``(w, x, y, z)`` (real part first, as in kornia);
rotation matrices act on column vectors. Euler angles are in degrees; ``order`` names the
axis of each angle in turn:

* lower case (``"xyz"``, default): *extrinsic*, about the fixed world axes, the first letter
  applied first: ``"xyz"`` is ``R = Rz(c) Ry(b) Rx(a)`` (Blender's "XYZ Euler" mode, scipy's
  ``"xyz"``, kornia's ``quaternion_from_euler``);
* upper case (``"XYZ"``): *intrinsic*, about the rotating body axes: ``R = Rx(a) Ry(b) Rz(c)``.

A time line is sampled at ``frame_times(count, fps)`` (frame i at t = i / fps). Object
poses are :class:`Keyframes` evaluated by :func:`transform_at` (object -> world matrices);
cameras follow :func:`look_at_path` or :func:`orbit_path` (world -> view matrices, the
conventions of :mod:`torchraster.camera`). Everything is differentiable with respect to the
key values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from . import camera
from ._validate import check_tensor

#: Largest frame count accepted by :func:`frame_times` (a typo such as 1e9 frames fails early).
MAX_FRAMES: int = 100_000

INTERPOLATIONS = ("linear", "step")

_AXES = {"x": 0, "y": 1, "z": 2}


def _float_tensor(name: str, value: object, dtype: torch.dtype | None = None,
                  device: torch.device | None = None) -> torch.Tensor:
    """A floating tensor from a tensor / number / nested list; keeps a tensor's dtype."""
    if isinstance(value, torch.Tensor):
        if not value.is_floating_point():
            value = value.to(dtype or torch.float32)
        return value if device is None else value.to(device)
    try:
        return torch.as_tensor(value, dtype=dtype or torch.float32, device=device)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name}: expected numbers or a tensor, got {value!r}") from None


# --------------------------------------------------------------------------- quaternions


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a b`` of ``(..., 4)`` quaternions (w, x, y, z), broadcast.

    As rotations, ``a b`` applies ``b`` first, then ``a``. Returns ``(..., 4)``.
    """
    check_tensor("a", a, (*[None] * (a.dim() - 1), 4), floating=True)
    check_tensor("b", b, (*[None] * (b.dim() - 1), 4), floating=True)
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    av, bv = torch.broadcast_tensors(av, bv)
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    v = aw * bv + bw * av + torch.linalg.cross(av, bv, dim=-1)
    return torch.cat([w, v], dim=-1)


def _check_order(order: str) -> tuple[list[int], bool]:
    if (not isinstance(order, str) or len(order) != 3 or not (order.islower() or order.isupper())
            or any(c not in _AXES for c in order.lower())
            or order[0].lower() == order[1].lower() or order[1].lower() == order[2].lower()):
        raise ValueError(f"order: expected three axis letters, all lower case (extrinsic) or "
                         f"all upper case (intrinsic), no axis twice in a row, e.g. 'xyz', "
                         f"'ZYX', 'zxz'; got {order!r}")
    return [_AXES[c] for c in order.lower()], order.isupper()


def quaternion_from_euler(angles_deg: torch.Tensor | Sequence[float],
                          order: str = "xyz") -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` (w, x, y, z) of Euler angles ``(..., 3)`` in degrees.

    ``order``: see the module docstring (lower case extrinsic, upper case intrinsic).
    The quaternion of an angle a about a unit axis e is ``(cos a/2, sin a/2 e)``; the
    three are multiplied in the order they act (Shoemake, "Euler angle conversion",
    Graphics Gems IV). Differentiable.

    Example:
        >>> quaternion_from_euler([0.0, 0.0, 90.0])  # (cos 45 deg, sin 45 deg * z axis)
        tensor([0.7071, 0.0000, 0.0000, 0.7071])
    """
    axes, intrinsic = _check_order(order)
    angles = _float_tensor("angles_deg", angles_deg)
    check_tensor("angles_deg", angles, (*[None] * (angles.dim() - 1), 3), floating=True,
                 finite=True)
    half = torch.deg2rad(angles) / 2
    quats = []
    for i, axis in enumerate(axes):
        w = torch.cos(half[..., i])
        s = torch.sin(half[..., i])
        comps = [w] + [s if k == axis else torch.zeros_like(s) for k in range(3)]
        quats.append(torch.stack(comps, dim=-1))
    # extrinsic: the first rotation is applied first -> rightmost factor; intrinsic: leftmost.
    q0, q1, q2 = quats
    if intrinsic:
        return quaternion_multiply(quaternion_multiply(q0, q1), q2)
    return quaternion_multiply(quaternion_multiply(q2, q1), q0)


def _check_quaternion(name: str, q: torch.Tensor) -> torch.Tensor:
    check_tensor(name, q, (*[None] * (q.dim() - 1), 4), floating=True, finite=True)
    norm = q.detach().norm(dim=-1)
    if q.numel() and bool((norm < 1e-12).any()):
        idx = torch.nonzero(norm < 1e-12)[0].tolist()
        raise ValueError(f"{name}: the quaternion at index {idx} has zero norm; expected a "
                         "rotation (w, x, y, z), e.g. [1, 0, 0, 0] for none")
    return q


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` (w, x, y, z).

    The quaternions are normalised first (any non-zero scale is the same rotation); a zero
    quaternion raises. Uses kornia's ``quaternion_to_rotation_matrix``. Differentiable.
    """
    _check_quaternion("q", q)
    from kornia.geometry.conversions import quaternion_to_rotation_matrix  # lazy: ~0.2 s

    return quaternion_to_rotation_matrix(q)


def _safe_norm(x: torch.Tensor) -> torch.Tensor:
    """|x| over the last dim with a zero (not NaN) gradient at x = 0."""
    sq = (x * x).sum(-1)
    return torch.sqrt(sq.clamp_min(torch.finfo(x.dtype).tiny))


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Spherical linear interpolation of quaternions, the shortest way round.

    q0, q1: ``(..., 4)`` (normalised here), t: a float or a tensor broadcasting against
    ``q0[..., 0]``. Returns unit quaternions ``(..., 4)``: q0 at t = 0, q1 (or -q1, the same
    rotation, when that is nearer) at t = 1. Formula (Shoemake 1985):
    ``sin((1 - t) theta) / sin(theta) q0 + sin(t theta) / sin(theta) q1``, written with
    sinc so that it stays exact and differentiable as q0 -> +-q1 (theta -> 0), and theta
    from ``2 atan2(|q0 - q1|, |q0 + q1|)``, accurate at small angles where acos is not.

    Example:
        >>> identity = torch.tensor([1.0, 0, 0, 0])
        >>> slerp(identity, quaternion_from_euler([0.0, 90.0, 0.0]), 0.5)  # 45 deg about y
        tensor([0.9239, 0.0000, 0.3827, 0.0000])
    """
    q0 = _check_quaternion("q0", q0)
    q1 = _check_quaternion("q1", q1)
    q0 = q0 / q0.norm(dim=-1, keepdim=True)
    q1 = q1 / q1.norm(dim=-1, keepdim=True)
    t = _float_tensor("t", t, q0.dtype, q0.device)
    sign = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q0.dtype)
    q1 = q1 * sign  # shortest path: q and -q are one rotation
    theta = 2 * torch.atan2(_safe_norm(q0 - q1), _safe_norm(q0 + q1))  # in [0, pi/2]
    # sin(u theta) / sin(theta) = u sinc(u theta) / sinc(theta); torch.sinc(x) = sin(pi x)/(pi x)
    sinc_theta = torch.sinc(theta / math.pi)
    w0 = (1 - t) * torch.sinc((1 - t) * theta / math.pi) / sinc_theta
    w1 = t * torch.sinc(t * theta / math.pi) / sinc_theta
    out = w0.unsqueeze(-1) * q0 + w1.unsqueeze(-1) * q1
    return out / out.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------- keyframes


def check_times(name: str, times: object, dtype: torch.dtype = torch.float32,
                device: torch.device | None = None) -> torch.Tensor:
    """Key times ``(K,)``, K >= 1, finite and strictly increasing, as a ``dtype`` tensor.

    Errors name the keyframe: ``times: keyframes 2 and 3 have the same time 1.0``.
    """
    t = _float_tensor(name, times, dtype, device).to(dtype)
    check_tensor(name, t, ("K",), floating=True)
    if t.shape[0] == 0:
        raise ValueError(f"{name}: expected at least one keyframe, got none")
    values = t.detach().tolist()
    for i, v in enumerate(values):
        if not math.isfinite(v):
            raise ValueError(f"{name}[{i}]: expected a finite time, got {v}")
    for i in range(1, len(values)):
        a, b = values[i - 1], values[i]
        if b == a:
            raise ValueError(f"{name}: keyframes {i - 1} and {i} have the same time {a}; "
                             "times must be strictly increasing")
        if b < a:
            raise ValueError(f"{name}: keyframe {i} (t = {b}) comes before keyframe {i - 1} "
                             f"(t = {a}); times must be strictly increasing")
    return t


def check_keyed(name: str, value: object, k: int, c: int, fill: float,
                dtype: torch.dtype = torch.float32,
                device: torch.device | None = None) -> torch.Tensor:
    """Keyed values ``(K, C)`` (finite) as a ``dtype`` tensor; None gives ``fill``
    everywhere. Errors name the field and the key index."""
    if value is None:
        return torch.full((k, c), fill, dtype=dtype, device=device)
    v = _float_tensor(name, value, dtype, device).to(dtype)
    check_tensor(name, v, (k, c), floating=True)
    finite = torch.isfinite(v.detach()).all(dim=-1)
    if not bool(finite.all()):
        i = int(torch.nonzero(~finite)[0])
        raise ValueError(f"{name}[{i}]: expected finite values, got {v[i].tolist()}")
    return v


@dataclass(eq=False)
class Keyframes:
    """Keyframed object -> world transforms: scale, then rotate, then translate.

    Fields (tensors or nested lists; K >= 1 keys; all held in the widest floating dtype of
    the tensor fields, at least float32):
        times: ``(K,)`` seconds, finite and strictly increasing.
        translation: ``(K, 3)``; None = zeros.
        rotation: ``(K, 4)`` quaternions (w, x, y, z), any non-zero norm; None = identity.
            Euler angles: build with :meth:`from_records` or :func:`quaternion_from_euler`.
        scale: ``(K, 3)`` or ``(K,)`` (uniform), positive; None = ones.
        interpolation: ``"linear"`` (lerp translation and scale, slerp rotation) or
            ``"step"`` (each key holds until the next).
    Before the first key and after the last the end values hold.
    """

    times: torch.Tensor
    translation: torch.Tensor | None = None
    rotation: torch.Tensor | None = None
    scale: torch.Tensor | None = None
    interpolation: str = "linear"

    def __post_init__(self) -> None:
        fields = (self.times, self.translation, self.rotation, self.scale)
        dtype, device = torch.float32, None
        for v in fields:
            if isinstance(v, torch.Tensor) and v.is_floating_point():
                dtype = torch.promote_types(dtype, v.dtype)
                device = v.device if device is None else device
        self.times = times = check_times("times", self.times, dtype, device)
        k, device = times.shape[0], times.device
        self.translation = check_keyed("translation", self.translation, k, 3, 0.0, dtype,
                                       device)
        rot = check_keyed("rotation", self.rotation, k, 4, 0.0, dtype, device)
        if self.rotation is None:
            rot = rot.index_fill(1, torch.tensor([0], device=device), 1.0)  # identity
        norm = rot.detach().norm(dim=-1)
        for i in range(k):
            if float(norm[i]) < 1e-12:
                raise ValueError(f"rotation[{i}]: zero quaternion; expected (w, x, y, z) "
                                 "with a non-zero norm, e.g. [1, 0, 0, 0]")
        self.rotation = rot
        scale = self.scale
        if scale is not None:
            scale = _float_tensor("scale", scale, dtype, device)
            if scale.dim() == 1:
                check_tensor("scale", scale, (k,), floating=True)
                scale = scale.unsqueeze(-1).expand(k, 3)
        scale = check_keyed("scale", scale, k, 3, 1.0, dtype, device)
        bad = (scale.detach() <= 0).any(dim=-1)
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0])
            raise ValueError(f"scale[{i}]: expected positive values, got {scale[i].tolist()} "
                             "(a zero scale is degenerate, a negative one mirrors the object "
                             "and flips its faces' winding)")
        self.scale = scale
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, "
                             f"got {self.interpolation!r}")

    @classmethod
    def from_records(cls, records: Sequence[Mapping[str, object]],
                     interpolation: str = "linear", euler_order: str = "xyz") -> Keyframes:
        """Keyframes from one mapping per key (the shape of a YAML list of keys).

        Each record: ``time`` (required); ``translation`` [x, y, z] (default 0);
        ``rotation`` [w, x, y, z] *or* ``euler_deg`` [a, b, c] in ``euler_order``
        (default identity); ``scale`` a number or [sx, sy, sz] (default 1).
        Unknown keys raise (a misspelt field must not be ignored silently).
        """
        if not isinstance(records, Sequence) or isinstance(records, str) or not records:
            raise ValueError("records: expected a non-empty list of keyframes "
                             "({time: ..., translation: ..., ...})")
        known = {"time", "translation", "rotation", "euler_deg", "scale"}
        times, trans, rots, scales = [], [], [], []
        for i, rec in enumerate(records):
            where = f"records[{i}]"
            if not isinstance(rec, Mapping):
                raise TypeError(f"{where}: expected a mapping, got {type(rec).__name__}")
            extra = set(rec) - known
            if extra:
                raise ValueError(f"{where}: unknown field(s) {sorted(extra)}; "
                                 f"expected {sorted(known)}")
            if "time" not in rec:
                raise ValueError(f"{where}: missing 'time'")
            if "rotation" in rec and "euler_deg" in rec:
                raise ValueError(f"{where}: give 'rotation' (quaternion) or 'euler_deg', "
                                 "not both")
            times.append(_record_value(f"{where}.time", rec["time"], ()))
            trans.append(_record_value(f"{where}.translation",
                                       rec.get("translation", [0.0, 0.0, 0.0]), (3,)))
            if "euler_deg" in rec:
                e = _record_value(f"{where}.euler_deg", rec["euler_deg"], (3,))
                rots.append(quaternion_from_euler(e.double(), euler_order).float())
            else:
                rots.append(_record_value(f"{where}.rotation",
                                          rec.get("rotation", [1.0, 0.0, 0.0, 0.0]), (4,)))
            s = _record_value(f"{where}.scale", rec.get("scale", 1.0), None)
            if s.shape not in ((), (3,)):
                raise ValueError(f"{where}.scale: expected a number or 3 numbers, "
                                 f"got {s.tolist()}")
            scales.append(s.expand(3))
        return cls(times=torch.stack(times), translation=torch.stack(trans),
                   rotation=torch.stack(rots), scale=torch.stack(scales),
                   interpolation=interpolation)


def _record_value(name: str, value: object, shape: tuple[int, ...] | None) -> torch.Tensor:
    """One field of a keyframe record as a finite float32 tensor of ``shape``."""
    if isinstance(value, bool | str) or (isinstance(value, Sequence)
                                         and any(isinstance(v, bool | str) for v in value)):
        raise TypeError(f"{name}: expected numbers, got {value!r}")
    v = _float_tensor(name, value).float()
    if shape is not None and tuple(v.shape) != shape:
        want = "a number" if shape == () else f"{shape[0]} numbers"
        raise ValueError(f"{name}: expected {want}, got {value!r}")
    if not bool(torch.isfinite(v).all()):
        raise ValueError(f"{name}: expected finite values, got {value!r}")
    return v


def _segments(times: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Index i of the key at or before each t (clamped to [0, K - 2]) and the fraction
    u in [0, 1] of the way to key i + 1 (0 before the first key, 1 after the last)."""
    k = times.shape[0]
    if k == 1:
        return torch.zeros_like(t, dtype=torch.long), torch.zeros_like(t)
    i = (torch.searchsorted(times.detach(), t.detach(), right=True) - 1).clamp(0, k - 2)
    t0, t1 = times[i], times[i + 1]
    u = ((t - t0) / (t1 - t0)).clamp(0, 1)
    return i, u


def _times(t: object, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    tt = _float_tensor("t", t, dtype, device)
    if tt.dim() == 0:
        tt = tt.reshape(1)
    check_tensor("t", tt, ("T",), floating=True, finite=True)
    return tt.to(dtype)


def _lerp_keys(times: torch.Tensor, values: torch.Tensor, t: torch.Tensor,
               interpolation: str) -> torch.Tensor:
    """Values ``(K, C)`` keyed at ``times (K,)`` evaluated at ``t (T,)`` -> ``(T, C)``."""
    i, u = _segments(times, t)
    if values.shape[0] == 1:
        return values.expand(t.shape[0], -1)
    if interpolation == "step":
        return values[torch.where(u >= 1, i + 1, i)]
    u = u.unsqueeze(-1)
    return values[i] * (1 - u) + values[i + 1] * u


def sample_keyframes(keys: Keyframes, t: torch.Tensor | Sequence[float] | float
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Translation ``(T, 3)``, unit rotation quaternion ``(T, 4)`` and scale ``(T, 3)`` of
    ``keys`` at times ``t (T,)`` (a float gives T = 1). Differentiable w.r.t. key values."""
    if not isinstance(keys, Keyframes):
        raise TypeError(f"keys: expected Keyframes, got {type(keys).__name__}")
    tt = _times(t, keys.times.dtype, keys.times.device)
    trans = _lerp_keys(keys.times, keys.translation, tt, keys.interpolation)
    scale = _lerp_keys(keys.times, keys.scale, tt, keys.interpolation)
    rot = keys.rotation / keys.rotation.norm(dim=-1, keepdim=True)
    if keys.interpolation == "step" or rot.shape[0] == 1:
        rot = _lerp_keys(keys.times, rot, tt, "step")
    else:
        i, u = _segments(keys.times, tt)
        rot = slerp(rot[i], rot[i + 1], u)
    return trans, rot, scale


def compose_transform(translation: torch.Tensor, rotation: torch.Tensor,
                      scale: torch.Tensor) -> torch.Tensor:
    """Matrices ``(..., 4, 4)`` of ``p -> R(q) (s * p) + translation``.

    translation ``(..., 3)``, rotation ``(..., 4)`` quaternions (w, x, y, z), scale
    ``(..., 3)``, same leading shape.
    """
    check_tensor("translation", translation, (*[None] * (translation.dim() - 1), 3),
                 floating=True, finite=True)
    check_tensor("scale", scale, (*translation.shape[:-1], 3), floating=True, finite=True)
    check_tensor("rotation", rotation, (*translation.shape[:-1], 4), floating=True)
    rs = quaternion_to_matrix(rotation) * scale.unsqueeze(-2)  # R diag(s): scales columns
    bottom = translation.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(*translation.shape[:-1], 1, 4)
    top = torch.cat([rs, translation.unsqueeze(-1)], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def transform_at(keys: Keyframes, t: torch.Tensor | Sequence[float] | float) -> torch.Tensor:
    """Object -> world matrices ``(T, 4, 4)`` of ``keys`` at times ``t (T,)``.

    Scale, then rotate, then translate: ``M = [R diag(s) | translation]``. At a key's time
    the result is that key's transform; times outside the keys hold the end values.
    Differentiable with respect to the key values (and times).

    Example:
        >>> keys = Keyframes(times=[0.0, 1.0], translation=[[0.0, 0, 0], [2.0, 0, 0]])
        >>> transform_at(keys, [0.5, 2.0])[:, :3, 3]  # halfway; after the last key: held
        tensor([[1., 0., 0.],
                [2., 0., 0.]])
    """
    return compose_transform(*sample_keyframes(keys, t))


# --------------------------------------------------------------------------- cameras and time


def look_at_path(times: torch.Tensor | Sequence[float],
                 eyes: torch.Tensor | Sequence[Sequence[float]],
                 targets: torch.Tensor | Sequence[Sequence[float]],
                 ups: torch.Tensor | Sequence[float] | None = None, *,
                 t: torch.Tensor | Sequence[float] | float,
                 interpolation: str = "linear") -> torch.Tensor:
    """World -> view matrices ``(T, 4, 4)`` of a camera moving through keyed eyes / targets.

    times ``(K,)`` strictly increasing; eyes, targets ``(K, 3)``; ups ``(K, 3)`` keyed,
    ``(3,)`` constant, or None (+y). Eye, target and up are interpolated linearly (or held,
    ``interpolation="step"``) at ``t (T,)``, holding the end values outside the keys, then
    passed to :func:`torchraster.camera.look_at` (looks down -z, +y up; a fallback up where
    the view is parallel to up).
    """
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, "
                         f"got {interpolation!r}")
    ref = next((v for v in (eyes, targets, times) if isinstance(v, torch.Tensor)
                and v.is_floating_point()), None)
    dtype = ref.dtype if ref is not None else torch.float32
    device = ref.device if ref is not None else None
    key_times = check_times("times", times, dtype, device)
    k, device = key_times.shape[0], key_times.device
    eyes_t = check_keyed("eyes", eyes, k, 3, 0.0, dtype, device)
    targets_t = check_keyed("targets", targets, k, 3, 0.0, dtype, device)
    tt = _times(t, dtype, device)
    eye = _lerp_keys(key_times, eyes_t, tt, interpolation)
    target = _lerp_keys(key_times, targets_t, tt, interpolation)
    same = (eye - target).detach().norm(dim=-1) == 0
    if bool(same.any()):
        j = int(torch.nonzero(same)[0])
        raise ValueError(f"look_at_path: at t = {float(tt[j])} the eye and the target "
                         f"coincide ({eye[j].tolist()})")
    up = None
    if ups is not None:
        ups_t = _float_tensor("ups", ups, dtype, device).to(dtype)
        if ups_t.dim() == 1:
            check_tensor("ups", ups_t, (3,), floating=True, finite=True)
            up = ups_t
        else:
            up = _lerp_keys(key_times, check_keyed("ups", ups_t, k, 3, 0.0, dtype, device),
                            tt, interpolation)
    return camera.look_at(eye, target, up)


def orbit_path(t: torch.Tensor | Sequence[float] | float, azimuth_deg0: float,
               degrees_per_second: float, elevation_deg: float, distance: float,
               target: torch.Tensor | Sequence[float] | None = None) -> torch.Tensor:
    """World -> view matrices ``(T, 4, 4)`` of a camera orbiting ``target`` (y up).

    Azimuth ``azimuth_deg0 + degrees_per_second * t`` (linear in time), constant elevation
    and distance, through :func:`torchraster.camera.orbit` (azimuth 0 looks from +z,
    positive azimuth moves towards +x; elevation above the xz-plane).
    """
    for name, v in (("azimuth_deg0", azimuth_deg0), ("degrees_per_second", degrees_per_second),
                    ("elevation_deg", elevation_deg), ("distance", distance)):
        if isinstance(v, torch.Tensor):
            if v.numel() != 1:
                raise ValueError(f"{name}: expected a scalar, got shape {tuple(v.shape)}")
            v = float(v)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"{name}: expected a finite number, got {v!r}")
    if not float(distance) > 0:
        raise ValueError(f"distance: expected > 0, got {float(distance)}")
    ref = t if isinstance(t, torch.Tensor) and t.is_floating_point() else None
    tt = _times(t, ref.dtype if ref is not None else torch.float32,
                ref.device if ref is not None else torch.device("cpu"))
    azimuth = azimuth_deg0 + degrees_per_second * tt
    return camera.orbit(azimuth, torch.as_tensor(elevation_deg, dtype=tt.dtype),
                        torch.as_tensor(distance, dtype=tt.dtype), target)


def frame_times(count: int, fps: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Times ``(count,)`` in seconds of frames 0 .. count - 1: frame i is at ``i / fps``.

    count: an int in [1, MAX_FRAMES]; fps: a finite number > 0. Computed in float64, then
    cast to ``dtype``.
    """
    if isinstance(count, bool) or not isinstance(count, int):
        if isinstance(count, float) and count.is_integer():
            count = int(count)
        else:
            raise TypeError(f"count: expected an integer number of frames, got {count!r}")
    if not 1 <= count <= MAX_FRAMES:
        raise ValueError(f"count: expected 1 <= count <= {MAX_FRAMES} frames, got {count}")
    if isinstance(fps, bool) or not isinstance(fps, int | float):
        raise TypeError(f"fps: expected a number, got {fps!r}")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite value > 0, got {fps}")
    return (torch.arange(count, dtype=torch.float64) / float(fps)).to(dtype)
