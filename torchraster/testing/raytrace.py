"""Ray-traced shadow reference: float64 brute-force ray-triangle tests (Möller-Trumbore).

An independent reference for the shadow maps of :mod:`torchraster.shading.shadows`: it
imports nothing from the engine and has no maps, no biases and no filters. A receiver point
is lit by a light when the segment (or ray) from it to the light crosses no caster triangle.

* :func:`shadow_rays`: hard shadows of a directional light (ray towards ``-direction``) or a
  point / spot light (segment to the light's position). ``(N,)`` visibility in {0, 1}.
* :func:`area_shadow_rays`: soft shadows of an area light, the fraction of ``samples`` fixed,
  stratified rays per point that reach it: a disc of radius ``radius`` centred on the light
  position and facing the receiver (point / spot), or a cone of angular diameter ``angle``
  degrees around ``-direction`` (directional: a disc at infinity, e.g. the sun's 0.53 deg).

Comparing with the engine: :func:`make_lights`, :func:`render_shadow_factor` and
:func:`grazing_plane_shot` (the only functions here that import ``torchraster``, lazily)
read the engine's shadow factor of a pixel as the ratio of a render with shadows to the same
render without (one light, no ambient) through the public ``Renderer``; :func:`reference_for`
traces rays from the same G-buffer positions and normals, :func:`mask_stats` compares
masks. Scenes: :func:`ground_scene`, :func:`sphere_on_plane`, :func:`field_of_spheres`.

Ray epsilon: each ray starts at ``point + eps * normal`` (``eps`` = :data:`RAY_EPSILON`,
1e-4 m for metre-scale scenes; scale it with the scene) and every triangle hit with
``0 < t < t_max`` occludes; ``t_max`` is the distance to the light (``inf`` for directional
lights). The visibility is occlusion only: no ``n . l`` term, receivers facing away from the
light are still traced.

Speed: triangles are sorted along a Morton curve and grouped into a fixed hierarchy of
bounding boxes (:data:`LEAF` triangles per leaf, :data:`BRANCH` children per box); a ray is
tested against a box's triangles only when it crosses the box (slab test): a cull that does
not change the result, every remaining pair is a plain Möller-Trumbore test. Memory is
bounded by ``max_pairs`` pairs per step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

#: Offset (m) of ray origins along the receiver's normal.
RAY_EPSILON: float = 1e-4
#: Ray-triangle pairs tested at once (bounds the float64 temporaries to ~ 30 * this * 8 B).
MAX_PAIRS: int = 2**20

F64 = torch.float64


def _spread_bits(x: torch.Tensor) -> torch.Tensor:
    """Interleave the low 10 bits of int64 ``x`` with two zero bits each (Morton code)."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def _morton_order(points: torch.Tensor) -> torch.Tensor:
    """``(N,)`` permutation sorting ``points`` ``(N, 3)`` along a 30-bit Morton curve."""
    lo, hi = points.amin(0), points.amax(0)
    q = ((points - lo) / (hi - lo).clamp_min(1e-300) * 1023).clamp(0, 1023).long()
    code = (_spread_bits(q[:, 0]) << 2) | (_spread_bits(q[:, 1]) << 1) | _spread_bits(q[:, 2])
    return torch.argsort(code)


def _slab(o: torch.Tensor, inv_d: torch.Tensor, t_max: torch.Tensor, lo: torch.Tensor,
          hi: torch.Tensor) -> torch.Tensor:
    """Whether rays ``o + t d`` ``(P, 1, 3)`` (given ``1 / d``, finite: zero components are
    replaced by a tiny number) cross boxes ``lo``/``hi`` ``(P, K, 3)`` for some ``t`` in
    ``[0, t_max]`` ``(P, 1)``: ``(P, K)`` bool. The caller pads the boxes: conservative."""
    t1, t2 = (lo - o) * inv_d, (hi - o) * inv_d
    enter = torch.minimum(t1, t2).amax(-1).clamp_min(0)
    return enter <= torch.minimum(torch.maximum(t1, t2).amin(-1), t_max)


def _moller_trumbore(o: torch.Tensor, d: torch.Tensor, t_max: torch.Tensor, v0: torch.Tensor,
                     e1: torch.Tensor, e2: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Hits of rays ``o + t d`` ``(P, 1, 3)`` (unit ``d``), ``0 < t < t_max`` ``(P, 1)``, with
    triangles ``v0, v0 + e1, v0 + e2`` ``(P, K, 3)`` (both sides; Möller & Trumbore 1997):
    ``(P, K)`` bool. ``scale`` ``(P, K)``: ``|e1| |e2|``; a triangle (nearly) parallel to the
    ray (``|det| <= 1e-15 scale``), or degenerate, is never hit."""
    dx, dy, dz = d.unbind(-1)
    ax, ay, az = e1.unbind(-1)
    bx, by, bz = e2.unbind(-1)
    px, py, pz = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx  # d x e2
    det = ax * px + ay * py + az * pz
    ok = det.abs() > 1e-15 * scale
    inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
    sx, sy, sz = (o - v0).unbind(-1)
    u = (sx * px + sy * py + sz * pz) * inv
    qx, qy, qz = sy * az - sz * ay, sz * ax - sx * az, sx * ay - sy * ax  # s x e1
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (bx * qx + by * qy + bz * qz) * inv
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < t_max)


#: Triangles per leaf box and children per box of the cull hierarchy.
LEAF, BRANCH = 8, 8


def occluded(origins: torch.Tensor, dirs: torch.Tensor, t_max: torch.Tensor,
             positions: torch.Tensor, faces: torch.Tensor, max_pairs: int = MAX_PAIRS
             ) -> torch.Tensor:
    """Whether each ray hits a triangle.

    Args:
        origins, dirs: ``(R, 3)`` rays ``origin + t * dir`` (dirs need not be unit).
        t_max: ``(R,)`` hits count for ``0 < t < t_max`` (``inf``: unbounded).
        positions: ``(V, 3)`` vertices; faces: ``(F, 3)`` int64 triangles (both sides).
        max_pairs: ray-box / ray-triangle pairs tested per step (bounds memory).

    Returns:
        ``(R,)`` bool, computed in float64.
    """
    o, d = origins.to(F64), dirs.to(F64)
    length = d.norm(dim=-1)
    hit = torch.zeros(o.shape[0], dtype=torch.bool, device=o.device)
    if faces.numel() == 0 or o.shape[0] == 0:
        return hit
    d = d / length[:, None].clamp_min(1e-300)
    t_max = t_max.to(F64).to(o.device) * length  # in units of the unit direction
    tiny = torch.where(d < 0, -1e-200, 1e-200)
    inv_d = 1.0 / torch.where(d.abs() < 1e-200, tiny, d)
    tri = positions.to(F64).to(o.device)[faces.long().to(o.device)]  # (F, 3, 3)
    tri = tri[_morton_order(tri.mean(1))]
    sizes = [LEAF]  # triangles per box of each level, the root level first after reversal
    while -(-tri.shape[0] // sizes[-1]) > BRANCH:
        sizes.append(sizes[-1] * BRANCH)
    sizes.reverse()
    total = -(-tri.shape[0] // sizes[0]) * sizes[0]
    if total > tri.shape[0]:  # pad with zero-area triangles (never hit, point-sized boxes)
        pad = tri[-1:, :1].expand(total - tri.shape[0], 3, 3)
        tri = torch.cat([tri, pad])
    v0 = tri[:, 0]
    e1, e2 = tri[:, 1] - v0, tri[:, 2] - v0
    scale = e1.norm(dim=-1) * e2.norm(dim=-1)
    margin = 1e-9 * float((tri.amax((0, 1)) - tri.amin((0, 1))).abs().max()) + 1e-12
    # boxes of level k grouped by parent: (parents, fan, 3); the root level has one parent
    boxes = []
    for k, size in enumerate(sizes):
        fan = sizes[k - 1] // size if k else total // size
        t = tri.view(-1, fan, size, 3, 3)
        boxes.append((t.amin((2, 3)) - margin, t.amax((2, 3)) + margin))
    leaf = [x.view(-1, LEAF, 3) for x in (v0, e1, e2)] + [scale.view(-1, LEAF)]

    def descend(level: int, ray: torch.Tensor, parent: torch.Tensor) -> None:
        """Test rays ``ray`` ``(P,)`` against the children of their crossed box ``parent``
        ``(P,)`` of the level above (the triangles below the leaf level)."""
        if ray.numel() == 0:
            return
        fan = LEAF if level == len(sizes) else boxes[level][0].shape[1]
        if ray.numel() * fan > max_pairs:
            step = max(1, max_pairs // fan)
            for k in range(0, ray.numel(), step):
                descend(level, ray[k:k + step], parent[k:k + step])
            return
        keep = ~hit[ray]  # rays occluded by an earlier chunk are done
        ray, parent = ray[keep], parent[keep]
        ro, rt_ = o[ray][:, None], t_max[ray][:, None]
        if level == len(sizes):
            h = _moller_trumbore(ro, d[ray][:, None], rt_, *(x[parent] for x in leaf))
            hit[ray[h.any(1)]] = True
            return
        lo, hi = boxes[level]
        cross = _slab(ro, inv_d[ray][:, None], rt_, lo[parent], hi[parent])  # (P, fan)
        pair, child = cross.nonzero(as_tuple=True)
        descend(level + 1, ray[pair], parent[pair] * fan + child)

    rays = torch.arange(o.shape[0], device=o.device)
    descend(0, rays, torch.zeros_like(rays))
    return hit


def ray_origins(points: torch.Tensor, normals: torch.Tensor, eps: float) -> torch.Tensor:
    """``(N, 3)`` float64 shadow-ray origins: ``points`` moved ``eps`` along their unit
    ``normals`` (both ``(N, 3)``)."""
    n = normals.to(F64)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return points.to(F64) + eps * n


def shadow_rays(points: torch.Tensor, normals: torch.Tensor, positions: torch.Tensor,
                faces: torch.Tensor, *, direction: torch.Tensor | None = None,
                light_position: torch.Tensor | None = None, eps: float = RAY_EPSILON
                ) -> torch.Tensor:
    """Hard-shadow visibility of receivers by one light (give exactly one of the two).

    Args:
        points: ``(N, 3)`` receiver positions; normals: ``(N, 3)`` their normals (origin
            offset ``eps`` along them).
        positions: ``(V, 3)`` caster vertices; faces: ``(F, 3)`` caster triangles.
        direction: ``(3,)`` travel direction of a directional light (rays go to
            ``-direction``, unbounded).
        light_position: ``(3,)`` position of a point / spot light (segments end there).
        eps: ray origin offset along the normal (m).

    Returns:
        ``(N,)`` float64: 1 lit, 0 occluded.
    """
    o = ray_origins(points, normals, eps)
    if (direction is None) == (light_position is None):
        raise ValueError("shadow_rays: give exactly one of direction / light_position")
    if direction is not None:
        d = -torch.as_tensor(direction, dtype=F64, device=o.device).expand_as(o)
        t_max = torch.full((o.shape[0],), math.inf, dtype=F64, device=o.device)
    else:
        d = torch.as_tensor(light_position, dtype=F64, device=o.device) - o
        t_max = torch.ones(o.shape[0], dtype=F64, device=o.device)
    return 1.0 - occluded(o, d, t_max, positions, faces).to(F64)


def disc_samples(samples: int, dtype: torch.dtype = F64) -> torch.Tensor:
    """``(m * m, 2)`` fixed stratified points in the unit disc, ``m = ceil(sqrt(samples))``:
    the cell centres of an m x m grid through Shirley & Chiu's (1997) concentric map (equal
    area, so each point stands for the same share of the disc)."""
    m = max(1, math.ceil(math.sqrt(samples)))
    c = (torch.arange(m, dtype=F64) + 0.5) / m * 2 - 1
    a, b = torch.meshgrid(c, c, indexing="ij")
    a, b = a.flatten(), b.flatten()
    first = a.abs() > b.abs()
    r = torch.where(first, a, b)
    phi = torch.where(first, (math.pi / 4) * b / torch.where(a == 0, 1.0, a),
                      math.pi / 2 - (math.pi / 4) * a / torch.where(b == 0, 1.0, b))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], -1).to(dtype)


def _frame(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors ``(N, 3)`` perpendicular to unit ``w`` ``(N, 3)`` and each other."""
    helper = torch.zeros_like(w)
    x_major = w[:, 0].abs() < 0.9
    helper[:, 0] = torch.where(x_major, 1.0, 0.0)
    helper[:, 1] = torch.where(x_major, 0.0, 1.0)
    u = torch.linalg.cross(w, helper)
    u = u / u.norm(dim=-1, keepdim=True)
    return u, torch.linalg.cross(w, u)


def area_shadow_rays(points: torch.Tensor, normals: torch.Tensor, positions: torch.Tensor,
                     faces: torch.Tensor, *, direction: torch.Tensor | None = None,
                     angle: float | None = None, light_position: torch.Tensor | None = None,
                     radius: float | None = None, samples: int = 64,
                     eps: float = RAY_EPSILON, max_rays: int = 2**20) -> torch.Tensor:
    """Fractional visibility of an area light: a disc light of radius ``radius`` (m) at
    ``light_position`` facing each receiver, or a directional light of angular diameter
    ``angle`` (degrees) around ``-direction``.

    Args:
        points, normals: ``(N, 3)`` receivers (origins offset ``eps`` along the normal).
        positions: ``(V, 3)``; faces: ``(F, 3)`` casters.
        direction, angle: a directional light (travel direction ``(3,)``, full cone angle).
        light_position, radius: a disc light (centre ``(3,)``, radius).
        samples: rays per point (rounded up to a square: :func:`disc_samples`).
        max_rays: rays traced per step (points are processed in chunks).

    Returns:
        ``(N,)`` float64 in [0, 1]: the fraction of the light's samples that are unoccluded.
    """
    if (direction is None) == (light_position is None):
        raise ValueError("area_shadow_rays: give exactly one of direction / light_position")
    o_all = ray_origins(points, normals, eps)
    disc = disc_samples(samples).to(o_all.device)  # (S, 2)
    n_s = disc.shape[0]
    out = torch.empty(o_all.shape[0], dtype=F64, device=o_all.device)
    per = max(1, max_rays // n_s)
    for k in range(0, o_all.shape[0], per):
        o = o_all[k:k + per]
        if direction is not None:
            w = -torch.as_tensor(direction, dtype=F64, device=o.device)
            w = (w / w.norm()).expand_as(o)
            u, v = _frame(w)
            tan_half = math.tan(math.radians(angle) / 2)
            d = (w[:, None] + tan_half * (disc[None, :, :1] * u[:, None]
                                          + disc[None, :, 1:] * v[:, None]))
            t_max = torch.full(d.shape[:2], math.inf, dtype=F64, device=o.device)
        else:
            c = torch.as_tensor(light_position, dtype=F64, device=o.device)
            to_c = c - o
            w = to_c / to_c.norm(dim=-1, keepdim=True).clamp_min(1e-300)
            u, v = _frame(w)
            target = c + radius * (disc[None, :, :1] * u[:, None] + disc[None, :, 1:] * v[:, None])
            d = target - o[:, None]
            t_max = torch.ones(d.shape[:2], dtype=F64, device=o.device)
        hit = occluded(o[:, None].expand_as(d).reshape(-1, 3), d.reshape(-1, 3),
                       t_max.reshape(-1), positions, faces)
        out[k:k + per] = 1.0 - hit.view(-1, n_s).to(F64).mean(-1)
    return out


# ----------------------------------------------------------------- scenes and mask metrics


def ground_scene(casters: list[tuple[torch.Tensor, torch.Tensor]], plane_size: float,
                 dtype: torch.dtype = torch.float32
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Casters over a square ground plane at y = 0 (side ``plane_size``, centred, facing +y).

    Args:
        casters: ``[(vertices (Vi, 3), faces (Fi, 3)), ...]`` placed as given.
        plane_size: side of the plane (m).

    Returns:
        positions ``(V, 3)``, faces ``(F, 3)`` int64 (the plane's 2 triangles last) and
        ``(F,)`` bool: True on caster faces (the plane receives but does not cast).
    """
    h = plane_size / 2
    verts, tris, cast, base = [], [], [], 0
    for v, f in casters:
        verts.append(torch.as_tensor(v, dtype=dtype))
        tris.append(torch.as_tensor(f, dtype=torch.int64) + base)
        cast.append(torch.ones(len(f), dtype=torch.bool))
        base += len(v)
    verts.append(torch.tensor([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]], dtype=dtype))
    tris.append(torch.tensor([[0, 2, 1], [0, 3, 2]]) + base)
    cast.append(torch.zeros(2, dtype=torch.bool))
    return torch.cat(verts), torch.cat(tris), torch.cat(cast)


def icosphere(radius: float, centre, subdivisions: int = 3
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(V, 3)`` float64 vertices and ``(F, 3)`` faces of an icosphere (trimesh)."""
    import trimesh  # noqa: PLC0415

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return torch.tensor(s.vertices) + torch.tensor(centre, dtype=F64), torch.tensor(s.faces)


def sphere_on_plane() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A 1 m sphere (1280 faces) standing on a 4 m plane: :func:`ground_scene` outputs."""
    return ground_scene([icosphere(0.5, (0.0, 0.5, 0.0))], 4.0)


#: Camera (eye, target, vertical fov in degrees) and sun of :func:`field_of_spheres`.
FIELD_CAMERA = ((0.0, 1.7, 2.0), (0.0, 0.6, -10.0), 50.0)
FIELD_SUN = (-0.5, -0.8, 0.3)


def field_of_spheres(count: int = 10) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` spheres (radius 0.35-0.6 m, seeded) 2-40 m ahead of :data:`FIELD_CAMERA`
    over a 100 m plane (cascades): :func:`ground_scene` outputs."""
    gen = torch.Generator().manual_seed(1)
    casters = []
    for i in range(count):
        z = -2.0 - 38.0 * (i / (count - 1)) ** 1.5
        x = float(torch.rand(1, generator=gen) * 2 - 1) * (2 + 0.35 * -z)
        r = 0.35 + 0.25 * float(torch.rand(1, generator=gen))
        casters.append(icosphere(r, (x, r, z)))
    return ground_scene(casters, 100.0)


def _dilate(mask: torch.Tensor, radius: int) -> torch.Tensor:
    """Binary dilation of ``(H, W)`` bool by a (2 radius + 1)^2 square."""
    if radius <= 0:
        return mask
    x = mask[None, None].to(F64)
    return torch.nn.functional.max_pool2d(x, 2 * radius + 1, 1, radius)[0, 0] > 0


def mask_stats(ours: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor, band: int = 2
               ) -> dict[str, float]:
    """Compare shadow masks (visibility < 0.5 = shadowed) over the ``valid`` pixels.

    Args:
        ours, ref: ``(H, W)`` visibility of the tested renderer and of the reference.
        valid: ``(H, W)`` bool: receivers that the light reaches when nothing occludes.
        band: pixels within ``band`` of a reference boundary (shadowed next to lit, or
            either next to an invalid pixel) are left out of the acne / peter-panning rates.

    Returns:
        ``iou`` of the shadowed sets; ``acne``: share of the reference-lit pixels (outside
        the band) that we shadow; ``peter``: share of the reference-shadowed pixels
        (outside the band) that we light; the pixel counts ``n_lit``, ``n_shadow``,
        ``n_acne``, ``n_peter``.
    """
    a, r = (ours < 0.5) & valid, (ref < 0.5) & valid
    union = int((a | r).sum())
    iou = int((a & r).sum()) / union if union else 1.0
    edge = (_dilate(r, 1) & ~r) | (_dilate(~r & valid, 1) & r) | _dilate(~valid, 1)
    core = valid & ~_dilate(edge, band)
    lit, shadow = core & ~r, core & r
    n_acne, n_peter = int((lit & a).sum()), int((shadow & ~a).sum())
    n_lit, n_shadow = int(lit.sum()), int(shadow.sum())
    return {"iou": iou, "acne": n_acne / max(n_lit, 1), "peter": n_peter / max(n_shadow, 1),
            "n_lit": n_lit, "n_shadow": n_shadow, "n_acne": n_acne, "n_peter": n_peter}


# ------------------------------------------------------------- the engine side of a comparison

#: Lights of the sphere-on-a-plane scenes of the tests and benchmarks (metres, radians).
LIGHTS = {"directional": {"direction": (-1.0, -2.0, -0.5)},
          "spot": {"position": (1.0, 2.5, 0.5), "direction": (-1.0, -2.5, -0.5), "cone": 0.8},
          "point": {"position": (1.0, 1.6, 0.5)}}


def make_lights(kind: str, settings=None, *, direction=None, position=None, cone=None,
                cast: bool = True, count: int = 1, batch: int = 1):
    """``torchraster.Lights`` with ``count`` identical lights of ``kind`` (defaults:
    :data:`LIGHTS`) casting shadows (``cast``) with ``settings`` (a ``ShadowSettings``)."""
    import torchraster as tr  # noqa: PLC0415 (the reference itself never imports the engine)

    spec = dict(LIGHTS[kind])
    spec.update({k: v for k, v in (("direction", direction), ("position", position),
                                   ("cone", cone)) if v is not None})

    def full(value) -> torch.Tensor:
        return torch.tensor(value, dtype=torch.float32).expand(batch, count, *(
            (len(value),) if isinstance(value, (tuple, list)) else ())).clone()

    common = {"color": full((1.0, 1.0, 1.0)), "shadow": settings,
              "cast_shadows": torch.full((batch, count), cast)}
    if kind == "directional":
        part = tr.DirectionalLights(direction=full(spec["direction"]), intensity=full(3.0),
                                    **common)
    elif kind == "spot":
        part = tr.SpotLights(position=full(spec["position"]), direction=full(spec["direction"]),
                             intensity=full(10.0), outer_cone_angle=full(spec["cone"]), **common)
    else:
        part = tr.PointLights(position=full(spec["position"]), intensity=full(5.0), **common)
    return tr.Lights(**{kind: part})


def ray_light(lights) -> dict[str, torch.Tensor]:
    """The first light of ``lights`` as :func:`shadow_rays` keywords (``direction`` or
    ``light_position``, ``(3,)``)."""
    if lights.directional is not None:
        return {"direction": lights.directional.direction[0, 0]}
    return {"light_position": (lights.spot or lights.point).position[0, 0]}


@dataclass
class Shot:
    """The shadow factor of one render.

    Attributes:
        vis: ``(H, W)`` the engine's visibility (1 where not ``valid``).
        valid: ``(H, W)`` bool: receivers the light reaches with ``n . l > min_cos``.
        position, normal: ``(3, H, W)`` the G-buffer.
        plan: the render's ``RenderPlan``; image: ``(3, H, W)`` the shadowed render.
    """

    vis: torch.Tensor
    valid: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor
    plan: object
    image: torch.Tensor


def render_shadow_factor(positions: torch.Tensor, faces: torch.Tensor, cast: torch.Tensor,
                         lights, view: torch.Tensor, proj: torch.Tensor, res: int = 256,
                         receive: torch.Tensor | None = None, min_cos: float = 0.1) -> Shot:
    """Render a white dielectric scene (``(V, 3)``, ``(F, 3)``, ``cast`` ``(F,)``) with one
    light with and without shadows; the visibility is their ratio where the unshadowed
    radiance is > 0 and ``n . l > min_cos`` (at the terminator a tessellated caster shadows
    itself in the reference, which biases deliberately hide)."""
    import torchraster as tr  # noqa: PLC0415

    material = tr.Material(metallic_factor=0.0, roughness_factor=0.8)
    scene = tr.RenderScene(positions, faces, materials=[material], cast_shadows=cast,
                           receive_shadows=receive)
    with torch.no_grad():
        on = tr.Renderer(res)(scene, view, proj, lights, channels={"position", "normal"})
        off = tr.Renderer(res, shadows=False)(scene, view, proj, lights)
    a, b = on.image[0].mean(0), off.image[0].mean(0)
    p, n = on.gbuffer["position"][0], on.gbuffer["normal"][0]
    light = ray_light(lights)
    if "direction" in light:
        to_light = -light["direction"].view(3, 1, 1).expand_as(p)
    else:
        to_light = light["light_position"].view(3, 1, 1) - p
    to_light = to_light / to_light.norm(dim=0, keepdim=True).clamp_min(1e-12)
    valid = (b > 1e-6 * b.max()) & ((n * to_light).sum(0) > min_cos)
    vis = torch.where(valid, a / b.clamp_min(1e-30), torch.ones_like(a))
    return Shot(vis, valid, p, n, on.plan, on.image[0])


def reference_for(shot: Shot, lights, positions: torch.Tensor, faces: torch.Tensor, *,
                  radius: float | None = None, angle: float | None = None,
                  samples: int = 36) -> torch.Tensor:
    """Ray-traced ``(H, W)`` float64 visibility at the valid pixels of ``shot`` (1 elsewhere)
    by the casters ``faces``: hard, or of an area light (disc ``radius`` / cone ``angle``)."""
    m = shot.valid.flatten()
    pts = shot.position.permute(1, 2, 0).reshape(-1, 3)[m]
    nrm = shot.normal.permute(1, 2, 0).reshape(-1, 3)[m]
    out = torch.ones(m.numel(), dtype=F64)
    light = ray_light(lights)
    if radius is None and angle is None:
        out[m] = shadow_rays(pts, nrm, positions, faces, **light)
    else:
        size = {"angle": angle} if angle is not None else {"radius": radius}
        out[m] = area_shadow_rays(pts, nrm, positions, faces, samples=samples, **size, **light)
    return out.view(shot.valid.shape)



def grazing_plane_shot(kind: str, elevation: float, settings, plane: float = 6.0,
                       res: int = 128, azimuth: float = 30.0) -> Shot:
    """A plane that casts and receives (nothing else) lit at ``elevation`` degrees:
    directional from ``azimuth``; spot / point 3 m from the plane's centre at the height
    that puts it ``elevation`` above the centre, and only the pixels that see the light at
    least that high are valid. Every valid pixel should be fully lit."""
    import torchraster as tr  # noqa: PLC0415

    positions, faces, _ = ground_scene([], plane)
    cast = torch.ones(2, dtype=torch.bool)
    e, a = math.radians(elevation), math.radians(azimuth)
    if kind == "directional":
        lights = make_lights(kind, settings, direction=(
            -math.cos(e) * math.sin(a), -math.sin(e), -math.cos(e) * math.cos(a)))
    else:
        h = 3 * math.tan(e)
        lights = make_lights(kind, settings, position=(-3.0, h, 0.0),
                             direction=(1.0, -h / 3, 0.0), cone=1.2)
    view = tr.camera.look_at([0.0, 3.0, 5.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    shot = render_shadow_factor(positions, faces, cast, lights, view, proj, res=res,
                                min_cos=0.0)
    if kind != "directional":
        to_light = ray_light(lights)["light_position"].view(3, 1, 1) - shot.position
        shot.valid &= to_light[1] / to_light.norm(dim=0) >= math.sin(e) - 1e-6
    return shot

__all__ = ["FIELD_CAMERA", "FIELD_SUN", "LIGHTS", "RAY_EPSILON", "Shot", "area_shadow_rays",
           "disc_samples", "field_of_spheres", "grazing_plane_shot", "ground_scene", "icosphere",
           "make_lights", "mask_stats", "occluded", "ray_light", "reference_for",
           "render_shadow_factor", "shadow_rays", "sphere_on_plane"]
