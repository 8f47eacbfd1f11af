"""Area lights: rectangles and discs shaded with linearly transformed cosines.

The Cook-Torrance radiance of a polygonal light of constant radiance ``Le`` is
``Le (kd F_d + (f0 A + B) F_s)`` per light and pixel (Heitz, Dupuy, Hill & Neubelt 2016,
"Real-time polygonal-light shading with linearly transformed cosines"):

* ``F_d``: the polygon's form factor, the cosine-weighted solid angle over pi of its part
  above the horizon (exact, :func:`~torchraster.shading.ltc.polygon_form_factor`): the
  Lambert term ``kd / pi`` integrated over the light.
* ``F_s``: the same integral of the polygon transformed by the inverse LTC matrix fitted to
  this renderer's GGX lobe ``D V (n.l)`` at the pixel's roughness and n.v
  (:mod:`~torchraster.shading.ltc`): the lobe's shape; ``f0 A + B`` is its Fresnel-weighted
  magnitude, the split-sum table the ambient and IBL paths also read.

A disc (ellipse) is shaded as the regular :data:`DISC_SIDES`-gon of the same area; with
rectangles in the same light set, rectangles repeat their vertices (degenerate edges add
0). Energy compensation scales ``F_s`` and ``kd`` as for punctual lights. Visibility
(shadows) multiplies each light's whole contribution.
"""

from __future__ import annotations

import math

import torch

from torchraster.numerics import diffuse_color, safe_normalize, specular_f0
from torchraster.shading.brdf import MIN_COS, MIN_ROUGHNESS
from torchraster.shading.energy import DFG_LUT_SAMPLES, DFG_LUT_SIZE, energy_terms
from torchraster.shading.ibl import dfg_lut, lookup_dfg
from torchraster.shading.lights import AreaLights
from torchraster.shading.ltc import form_factor_components, frame_rows, ltc_coefficients

#: Sides of the regular polygon a disc is shaded as (same area as the disc). Its form
#: factor's error against the exact disc, relative to the largest: below 4e-3 for
#: receivers a fifth of the radius away or farther, up to 7e-2 next to the rim at a
#: twentieth (8 sides: 4e-2 and 0.2; docs/benchmarks.md, section area).
DISC_SIDES: int = 16

#: Rectangle corners in (s, t) of ``position + s u + t v``, counter-clockwise about u x v.
_RECT = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def polygon_sides(lights: AreaLights) -> int:
    """K, the vertex count of the polygons :func:`polygon_corners` makes of ``lights``."""
    return DISC_SIDES if bool(lights.disc.any()) else 4


def polygon_corners(lights: AreaLights, item: int | None = None) -> torch.Tensor:
    """``(L, K, 3)`` world vertices of batch item ``item``'s lights (None: ``(B, L, K, 3)``
    of every item), counter-clockwise about ``u x v`` (K = 4 for rectangles only, else
    :data:`DISC_SIDES`; a rectangle then repeats its corners).

    Example:
        >>> one = torch.ones(1, 1)
        >>> panel = AreaLights(position=torch.zeros(1, 1, 3), u=torch.tensor([[[1.0, 0, 0]]]),
        ...                    v=torch.tensor([[[0.0, 1, 0]]]), color=one[..., None].expand(
        ...                        1, 1, 3), intensity=one)
        >>> polygon_corners(panel, 0)[0].tolist()  # counter-clockwise about +z
        [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]
    """
    fields = (lights.position, lights.u, lights.v, lights.disc)
    c, u, v, disc = fields if item is None else (t[item] for t in fields)
    dt, dev = c.dtype, c.device
    rect = torch.tensor(_RECT, dtype=dt, device=dev)  # (4, 2)
    if not bool(disc.any()):
        st = rect.expand(*c.shape[:-1], 4, 2)
    else:
        k = DISC_SIDES
        phi = torch.arange(k, dtype=torch.float64) * (2 * math.pi / k)
        # the k-gon of the disc's area: circumradius sqrt(2 pi / (k sin(2 pi / k)))
        scale = math.sqrt(2 * math.pi / (k * math.sin(2 * math.pi / k)))
        ring = (torch.stack([phi.cos(), phi.sin()], -1) * scale).to(dt).to(dev)  # (k, 2)
        pad = rect.repeat_interleave(k // 4, 0)  # each corner k/4 times: same polygon
        st = torch.where(disc[..., None, None], ring, pad)  # (..., k, 2)
    return c[..., None, :] + st[..., :1] * u[..., None, :] + st[..., 1:] * v[..., None, :]


def area_incidence(lights: AreaLights, position: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """What area lights send to points in the air (fog samples): the light's radiance times
    the solid angle ``Omega`` its polygon subtends from its emitting side (exact: Van
    Oosterom and Strackee 1983's triangle solid angle over a fan of the polygon), its mean
    direction ``l`` (``Phi / |Phi|``, ``Phi = integral of w dw`` over the polygon, exact:
    half the edges' angles times their planes' unit normals, Arvo 1995) and the mean cosine
    ``mu = |Phi| / Omega`` of its directions about ``l`` (1 for a small light). A
    Henyey-Greenstein phase of anisotropy g convolved with the light's spread is about
    the phase of anisotropy ``g mu`` towards ``l`` (Legendre coefficients multiply:
    ``g^k mu^k``; exact for ``g = 0``).

    Args:
        lights: L area lights of a batch of B scenes.
        position: ``(B, 3, H, W)`` world positions (m).

    Returns:
        ``l``: ``(B, L, 3, H, W)`` unit mean direction towards each light (0 behind a
        one-sided light and at its surface); ``E``: ``(B, L, 3, H, W)`` fluence
        ``color * intensity * Omega`` (lux, RGB); ``mu``: ``(B, L, 1, H, W)`` in [0, 1].
    """
    corners = polygon_corners(lights)  # (B, L, K, 3)
    rel = corners[..., None, None] - position[:, None, None]  # (B, L, K, 3, H, W)
    a = rel[:, :, :1]
    b, c = rel[:, :, 1:-1], rel[:, :, 2:]
    la, lb, lc = (torch.linalg.vector_norm(t, dim=3) for t in (a, b, c))
    num = (a * torch.linalg.cross(b, c, dim=3)).sum(3)
    den = (la * lb * lc + (a * b).sum(3) * lc + (a * c).sum(3) * lb + (b * c).sum(3) * la)
    ok = num * num + den * den > torch.finfo(num.dtype).tiny
    omega = 2 * torch.atan2(torch.where(ok, num, 0.0), torch.where(ok, den, 1.0))
    omega = omega.sum(2).abs()[:, :, None]  # (B, L, 1, H, W): the fan's triangles agree
    facing = torch.linalg.cross(lights.u, lights.v, dim=-1)[..., None, None]  # (B, L, 3, 1, 1)
    seen = ((position[:, None] - lights.position[..., None, None]) * facing).sum(
        2, keepdim=True) > 0
    seen = seen | lights.two_sided[..., None, None, None]
    # Phi: each edge (a, b) adds theta (a x b) / |a x b| / 2, a and b unit
    unit = safe_normalize(rel, dim=3)
    edge_b = unit.roll(-1, dims=2)
    cross = torch.linalg.cross(unit, edge_b, dim=3)
    sin = torch.linalg.vector_norm(cross, dim=3, keepdim=True)
    fine = sin > torch.finfo(sin.dtype).eps
    theta = torch.atan2(sin, (unit * edge_b).sum(3, keepdim=True))
    phi = 0.5 * (theta * cross / torch.where(fine, sin, 1.0) * fine).sum(2)  # (B, L, 3, H, W)
    towards = (phi * (lights.position[..., None, None] - position[:, None])).sum(
        2, keepdim=True)
    phi = torch.where(towards < 0, -phi, phi)  # the orientation of the polygon's edges
    length = torch.linalg.vector_norm(phi, dim=2, keepdim=True)
    mu = (length / omega.clamp_min(torch.finfo(omega.dtype).tiny)).clamp(0.0, 1.0)
    l = safe_normalize(phi, dim=2) * seen
    e = (lights.color * lights.intensity[..., None])[..., None, None] * (omega * seen)
    return l, e, mu


def area_lights(
    lights: AreaLights,
    item: int,
    position: torch.Tensor,
    normal: torch.Tensor,
    view: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
    roughness: torch.Tensor,
    visibility: torch.Tensor | None = None,
    multiscatter: bool = True,
) -> torch.Tensor:
    """Sum over the L area lights of batch item ``item`` of the Cook-Torrance radiance at
    M packed pixels of that item (the area-light form of
    :func:`~torchraster.shading.lighting.cook_torrance_lights`; arguments alike).

    Args:
        lights: area lights ``(B, L, ...)``.
        item: the batch item whose lights shade these pixels.
        position, normal, view: ``(3, M)`` world position, unit normal, unit direction to
            the eye.
        albedo: ``(3, M)``; metallic, roughness: ``(1, M)``.
        visibility: ``(L, M)`` fraction of each light reaching each pixel, or None.
        multiscatter: energy compensation as for punctual lights.

    Returns:
        ``(3, M)`` outgoing radiance.

    Example:
        >>> one = torch.ones(1, 1)
        >>> panel = AreaLights(position=torch.tensor([[[0.0, 0, 1]]]),  # 2 x 2 m, 1 m up,
        ...                    u=torch.tensor([[[1.0, 0, 0]]]),  # facing down (u x v = -z)
        ...                    v=torch.tensor([[[0.0, -1, 0]]]), color=one[..., None].expand(
        ...                        1, 1, 3), intensity=one)
        >>> z = torch.tensor([[0.0], [0], [1]])
        >>> rad = area_lights(panel, 0, 0 * z, z, z, torch.ones(3, 1), torch.zeros(1, 1),
        ...                   torch.ones(1, 1), multiscatter=False)
        >>> round(rad[0, 0].item(), 3)  # Lambert: form factor 0.554, plus a little specular
        0.56
    """
    corners = polygon_corners(lights, item)  # (L, K, 3)
    n_v = (normal * view).sum(0)  # (M,)
    nv = n_v.clamp(MIN_COS, 1.0)
    rough = roughness[0].clamp(MIN_ROUGHNESS, 1.0)
    frame = frame_rows(normal.unbind(0), view.unbind(0))  # rows t1, t2, n: 3 x (x, y, z)
    # the vertices relative to each pixel in its frame, component by component: (L, K, M)
    rel = [corners[..., k, None] - position[k] for k in range(3)]
    x, y, z = ((r[0] * rel[0]).addcmul_(r[1], rel[1]).addcmul_(r[2], rel[2]) for r in frame)
    diffuse = form_factor_components(x, y, z, dim=1)  # (L, M)
    a, b, c, d = ltc_coefficients(rough, nv)  # M^-1 = [[a, 0, b], [0, c, 0], [d, 0, 1]]
    specular = form_factor_components(a * x + b * z, c * y, d * x + z, dim=1)
    # emitting side: one-sided lights light the half-space u x v points to; both integrals
    # are positive there (counter-clockwise seen from the pixel), negative behind
    facing = torch.linalg.cross(lights.u[item], lights.v[item])  # (L, 3)
    side = (facing * lights.position[item]).sum(1, keepdim=True) - facing @ position  # (L, M)
    weight = torch.where(lights.two_sided[item][:, None], -torch.sign(side),
                         (side < 0).to(side.dtype))
    if visibility is not None:
        weight = weight * visibility
    diffuse, specular = diffuse * weight, specular * weight
    f0, kd = specular_f0(albedo, metallic), diffuse_color(albedo, metallic)
    lut = dfg_lut(DFG_LUT_SIZE, DFG_LUT_SAMPLES, device=f0.device, dtype=f0.dtype)
    scale, bias = lookup_dfg(lut, nv.view(1, 1, 1, -1), rough.view(1, 1, 1, -1))
    spec_albedo = f0 * scale.view(1, -1) + bias.view(1, -1)  # the lobe's norm, f0 A + B
    if multiscatter:
        ms, kd_scale = energy_terms(f0, nv[None], rough[None], lut)
        spec_albedo, kd = spec_albedo * ms, kd * kd_scale
    color = (lights.color[item] * lights.intensity[item][:, None]).T  # (3, L)
    return kd * (color @ diffuse) + spec_albedo * (color @ specular)
