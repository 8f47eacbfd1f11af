"""Deferred geometry pass: only the G-buffer channels that later passes ask for.

Everything is computed on the covered pixels only (packed, ``(C, N)``), then scattered into
``(B, C, H, W)`` images held by a :class:`GBuffer`. Each channel is computed only if
requested, and inputs a channel needs (UVs, tangents, textures) are interpolated or sampled
only if some requested channel needs them; :func:`required_inputs` states those
dependencies and is tested.

Channels (0 where nothing is covered unless said otherwise):

=========  ===========  =====================================================================
name       shape        meaning
=========  ===========  =====================================================================
depth      (B, 1, H, W) linear view depth (distance along the view axis); 0 where empty
position   (B, 3, H, W) world position (camera-relative renders add the origin back in the
                        render's dtype: float32 rounds a world coordinate of 1e6 by up to 0.03)
normal     (B, 3, H, W) unit world shading normal (normal map applied), facing the camera
albedo     (B, 3, H, W) linear base colour (factor x texture)
alpha      (B, 1, H, W) base colour alpha (coverage x material alpha)
metallic   (B, 1, H, W) factor x texture B channel
roughness  (B, 1, H, W) perceptual roughness, factor x texture G channel
ao         (B, 1, H, W) 1 + strength (occlusion R - 1); 1 where no texture
emissive   (B, 3, H, W) linear emitted radiance (factor x texture)
mask       (B, 1, H, W) 1 covered, 0 empty
face_id    (B, 1, H, W) int64 face index, -1 where empty
uv         (B, 2, H, W) texture coordinates
instance   (B, 1, H, W) int64 object id 1..N of the visible face (``face_object``), 0 where empty
semantic   (B, 1, H, W) int64 category id of that object (``object_category``), 0 where empty
object_c.  (B, 3, H, W) ``object_coords``: NOCS coordinates of the visible point
distance   (B, 1, H, W) Euclidean distance from the camera centre (ray length); 0 where empty
amodal     (B, N, H, W) bool: object k + 1's whole silhouette, as if drawn alone (Renderer only)
flow_fwd.  (B, 2, H, W) ``flow_forward``: pixels (x right, y down) the visible point moves to the
                        next frame (:mod:`~torchraster.motion`; Renderer only, ``next_frame``)
flow_bwd.  (B, 2, H, W) ``flow_backward``: the same to the previous frame (``previous_frame``)
*_valid    (B, 1, H, W) ``flow_forward_valid`` / ``flow_backward_valid``: 1 where the point is
                        in the other frame's view and not occluded there, else 0
motion     (B, 2, H, W) NDC xy now minus NDC xy at the previous frame (TAA motion vectors)
=========  ===========  =====================================================================

Label channels (face_id, instance, semantic, object_coords, distance, amodal and the flow /
motion channels) are exact: taken from the visible face, never averaged. When a supersampled
frame is reduced (:meth:`GBuffer.downsample`, factor s) they keep ONE sub-sample per output
pixel, the one nearest its centre (ties to the top-left): index ``(s - 1) // 2`` of each
``s x s`` block; the other float channels are box-filtered.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import torch

from ._validate import check_tensor
from .material import Material
from .mip_atlas import MipAtlas
from .numerics import safe_normalize
from .raster import Fragments, interpolate_packed, to_image
from .raster.interpolate import scatter_image
from .texture import MipTexture

#: Channel name -> number of image channels C ("N": one per object, known per scene).
CHANNEL_SIZES: dict[str, int | str] = {
    "depth": 1, "position": 3, "normal": 3, "albedo": 3, "alpha": 1, "metallic": 1,
    "roughness": 1, "ao": 1, "emissive": 3, "mask": 1, "face_id": 1, "uv": 2,
    "instance": 1, "semantic": 1, "object_coords": 3, "distance": 1, "amodal": "N",
    "flow_forward": 2, "flow_backward": 2, "flow_forward_valid": 1,
    "flow_backward_valid": 1, "motion": 2,
}
CHANNELS = tuple(CHANNEL_SIZES)
#: Channels reduced by picking one sub-sample per pixel (not box-filtered) in
#: :meth:`GBuffer.downsample`; names not in CHANNELS are ignored.
LABEL_CHANNELS = frozenset({
    "face_id", "instance", "semantic", "object_coords", "distance", "amodal",
    "flow_forward", "flow_backward", "flow_forward_valid", "flow_backward_valid", "motion"})
#: Channels :func:`geometry_pass` can return packed (:class:`PackedChannels`).
PACKABLE_CHANNELS = frozenset({"position", "normal", "albedo", "alpha", "metallic", "roughness",
                               "ao", "emissive"})
#: Channels that are not floating point.
_INTEGER_CHANNELS = {"face_id", "mask", "instance", "semantic", "amodal"}
#: Channels computed from the visible face's identity (``face_object``).
_IDENTITY_CHANNELS = {"instance", "semantic"}
_MATERIAL_CHANNELS = {"albedo", "alpha", "metallic", "roughness", "ao", "emissive", "normal"}
_SLOTS = {"albedo": "base_color", "alpha": "base_color", "metallic": "metallic_roughness",
          "roughness": "metallic_roughness", "ao": "occlusion", "emissive": "emissive",
          "normal": "normal"}


@dataclass(eq=False)
class PackedChannels:
    """G-buffer channels of the covered pixels only, kept packed instead of as images.

    ``values[name]`` is ``(C, N)`` (C from :data:`CHANNEL_SIZES`), column k the pixel at flat
    index ``pixels[k]`` = b*H*W + i*W + j, ``pixels`` ``(N,)`` int64 in ascending order (so
    each batch item's pixels are one run of columns). :func:`geometry_pass` returns the
    channels named in its ``packed`` argument this way (memory: no ``(B, C, H, W)`` frame
    for a channel that only :func:`~torchraster.shading.shade` reads, which lights the
    covered pixels packed anyway); :meth:`image` makes the frame when one is needed.
    """

    pixels: torch.Tensor
    values: dict[str, torch.Tensor]

    def __post_init__(self) -> None:
        check_tensor("PackedChannels.pixels", self.pixels, ("N",), integer=True)
        n = self.pixels.shape[0]
        for name, value in self.values.items():
            if name not in PACKABLE_CHANNELS:
                raise ValueError(f"PackedChannels.values: {name!r} is not one of "
                                 f"{sorted(PACKABLE_CHANNELS)}")
            check_tensor(f"PackedChannels.values[{name!r}]", value, (CHANNEL_SIZES[name], n),
                         floating=True)

    def image(self, name: str, shape: tuple[int, int, int]) -> torch.Tensor:
        """Channel ``name`` as a ``(B, C, H, W)`` image of ``shape`` (B, H, W), 0 where not
        covered (differentiable with respect to the packed values)."""
        return scatter_image(self.values[name], self.pixels, shape)

    def item_starts(self, b: int, h: int, w: int) -> list[int]:
        """First column of each batch item and N: ``(B + 1)`` ints."""
        edges = torch.arange(b + 1, device=self.pixels.device) * (h * w)
        return torch.searchsorted(self.pixels, edges).tolist()


@dataclass(eq=False)
class GBuffer(Mapping):
    """The per-pixel surface data of a frame: one ``(B, C, H, W)`` image per channel.

    Every channel is optional (None = not computed); the module table lists their shapes and
    meaning. All present channels share B, H and W (checked), so a G-buffer can be built by
    hand (e.g. analytic test scenes) as well as by :func:`geometry_pass`. Pass it to
    :func:`torchraster.shading.shade` by name: channels are fields, so ``metallic`` and
    ``roughness`` cannot be swapped by position. It is also a read-only mapping of the
    channels present (``gb["depth"]``, ``list(gb)``, ``gb.items()``, ``dict(gb)``).
    ``packed`` (not a channel) may hold channels of the covered pixels only
    (:class:`PackedChannels`, from ``geometry_pass(packed=...)``): ``shade`` reads them
    where the image is None.

    Example:
        >>> gb = GBuffer(albedo=torch.ones(1, 3, 2, 2), mask=torch.ones(1, 1, 2, 2))
        >>> gb.channels(), list(gb), gb["mask"].shape, "depth" in gb
        (['albedo', 'mask'], ['albedo', 'mask'], torch.Size([1, 1, 2, 2]), False)
    """

    depth: torch.Tensor | None = None
    position: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    albedo: torch.Tensor | None = None
    alpha: torch.Tensor | None = None
    metallic: torch.Tensor | None = None
    roughness: torch.Tensor | None = None
    ao: torch.Tensor | None = None
    emissive: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    face_id: torch.Tensor | None = None
    uv: torch.Tensor | None = None
    instance: torch.Tensor | None = None
    semantic: torch.Tensor | None = None
    object_coords: torch.Tensor | None = None
    distance: torch.Tensor | None = None
    amodal: torch.Tensor | None = None
    flow_forward: torch.Tensor | None = None
    flow_backward: torch.Tensor | None = None
    flow_forward_valid: torch.Tensor | None = None
    flow_backward_valid: torch.Tensor | None = None
    motion: torch.Tensor | None = None
    #: channels held packed (covered pixels only) instead of as images; not a channel
    #: itself (not listed, iterated or mapped), read by ``shade`` (see :class:`PackedChannels`)
    packed: PackedChannels | None = None

    def __post_init__(self) -> None:
        size = None
        for name in self.channels():
            value = getattr(self, name)
            check_tensor(f"GBuffer.{name}", value, ("B", CHANNEL_SIZES[name], "H", "W"),
                         floating=name not in _INTEGER_CHANNELS)
            bhw = (value.shape[0], value.shape[2], value.shape[3])
            if size is None:
                size, first = bhw, name
            elif bhw != size:
                raise ValueError(f"GBuffer.{name}: (B, H, W) = {bhw} differs from "
                                 f"GBuffer.{first}'s {size}")

    def channels(self) -> list[str]:
        """Names of the channels present, in table order."""
        return [name for name in CHANNELS if getattr(self, name) is not None]

    def __getitem__(self, name: str) -> torch.Tensor:
        value = getattr(self, name, None) if name in CHANNEL_SIZES else None
        if value is None:
            raise KeyError(f"G-buffer channel {name!r} is not present; present: "
                           f"{self.channels()}")
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self.channels())

    def __len__(self) -> int:
        return len(self.channels())

    def require(self, *names: str, by: str) -> None:
        """Raise a ValueError naming the missing channels that ``by`` needs."""
        missing = [n for n in names if getattr(self, n) is None and not (
            self.packed is not None and n in self.packed.values)]
        if missing:
            raise ValueError(f"{by}: needs G-buffer channel(s) {missing}; the GBuffer has "
                             f"{self.channels()}")

    def as_dict(self) -> dict[str, torch.Tensor]:
        """{channel: image} of the channels present."""
        return {name: getattr(self, name) for name in self.channels()}

    def replace(self, **channels: torch.Tensor | None) -> GBuffer:
        """A copy with some channels replaced (checked like the constructor)."""
        return dataclasses.replace(self, **channels)

    def downsample(self, factor: int) -> GBuffer:
        """Reduce a supersampled G-buffer: ``(B, C, s*H, s*W) -> (B, C, H, W)``.

        Label channels (:data:`LABEL_CHANNELS`) and integer channels take the sub-sample
        nearest each pixel centre, ties to the top-left: index ``(s - 1) // 2`` of each
        ``s x s`` block (an exact label, never a blend of two objects); the other float
        channels are box-filtered."""
        if factor == 1:
            return self
        k = (factor - 1) // 2
        out = {}
        for name, v in self.as_dict().items():
            out[name] = (v[:, :, k::factor, k::factor]
                         if name in LABEL_CHANNELS or not v.is_floating_point()
                         else torch.nn.functional.avg_pool2d(v, factor))
        return GBuffer(**out)


def check_channels(channels: Iterable[str]) -> set[str]:
    """Validate a set of channel names (error names the unknown ones)."""
    channels = set(channels)
    unknown = channels - set(CHANNELS)
    if unknown:
        raise ValueError(f"channels: unknown {sorted(unknown)}; expected some of {CHANNELS}")
    return channels


def required_inputs(channels: Iterable[str], materials: Sequence[Material | None]) -> set[str]:
    """Which inputs the requested channels need: a subset of
    {"position", "normal", "uv", "uv_derivatives", "tangent", "texture:<slot>"}."""
    channels = check_channels(channels)
    need: set[str] = set()
    if channels & {"position", "depth", "distance"}:
        need.add("position")
    if "normal" in channels:
        need.add("normal")
    for ch in channels & _MATERIAL_CHANNELS:
        slot = _SLOTS[ch]
        if any(m is not None and getattr(m, slot + "_texture") is not None for m in materials):
            need |= {"uv", "uv_derivatives", "texture:" + slot}
            if ch == "normal":
                need.add("tangent")
    if "uv" in channels:
        need.add("uv")
    return need


class MipCache:
    """Mip pyramids of constant textures kept across frames, least recently used first out
    (a :class:`~torchraster.texture.MipTexture` per texture, or a
    :class:`~torchraster.mip_atlas.MipAtlas` per tuple of a material's same-size textures).

    Keyed by the texture tensor's identity and version counter (an in-place edit of the
    texture invalidates its entry), the dtype and the device; an entry holds only a weak
    reference to the texture, so a texture that is freed drops out at the next lookup.
    Bounded by ``max_bytes`` of pyramid data. Textures that require grad are never cached
    (their pyramid must be rebuilt in every graph).

    Args:
        max_bytes: largest total size of the cached pyramids (default 512 MiB).
    """

    def __init__(self, max_bytes: int = 512 * 2**20) -> None:
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[tuple, tuple] = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached pyramids."""
        return sum(e[2] for e in self._entries.values())

    def get(self, raw: torch.Tensor | tuple[torch.Tensor, ...], build, dtype: torch.dtype,
            device: torch.device):
        """The cached ``build()`` result for texture ``raw`` (or a tuple of textures that
        ``build`` combines; built and stored on a miss)."""
        raws = raw if isinstance(raw, tuple) else (raw,)
        if any(r.requires_grad for r in raws):
            return build()
        self._entries = OrderedDict((k, e) for k, e in self._entries.items()
                                    if all(r() is not None for r in e[0]))  # drop freed ones
        key = (tuple((id(r), r._version) for r in raws), dtype, device)
        entry = self._entries.get(key)
        if entry is not None and all(r() is t for r, t in zip(entry[0], raws, strict=True)):
            self._entries.move_to_end(key)
            return entry[1]
        value = build()
        size = (value.nbytes if isinstance(value, MipAtlas) else
                sum(t.numel() * t.element_size() for t in getattr(value, "levels", [])))
        self._entries[key] = (tuple(weakref.ref(r) for r in raws), value, size)
        while self.nbytes > self.max_bytes and len(self._entries) > 1:
            self._entries.popitem(last=False)
        return value


def geometry_pass(
    frags: Fragments,
    channels: Iterable[str],
    *,
    positions: torch.Tensor,
    view: torch.Tensor,
    normals: torch.Tensor | None = None,
    uvs: torch.Tensor | None = None,
    tangents: torch.Tensor | None = None,
    face_material: torch.Tensor | None = None,
    materials: Sequence[Material | None] = (),
    texture_filter: str = "trilinear",
    mip_cache: MipCache | None = None,
    max_anisotropy: int = 16,
    face_object: torch.Tensor | None = None,
    object_category: torch.Tensor | None = None,
    object_coords: torch.Tensor | None = None,
    release_derivatives: bool = False,
    packed: Iterable[str] = (),
) -> GBuffer:
    """Compute the requested G-buffer channels (see the module table).

    Args:
        frags: from ``rasterize(..., derivatives=True)`` when textures are sampled
            trilinearly or anisotropically.
        channels: names from :data:`CHANNELS`.
        positions: ``(B, V, 3)`` or ``(V, 3)`` world positions.
        view: ``(B, 4, 4)`` world -> view matrices.
        normals: ``(B, V, 3)`` or ``(V, 3)`` vertex normals (required for ``normal``).
        uvs: ``(V, 2)`` or ``(B, V, 2)`` texture coordinates.
        tangents: ``(V, 4)`` or ``(B, V, 4)`` (xyz, handedness) for normal maps.
        face_material: ``(F,)`` int64 index into ``materials`` (None: material 0).
        materials: the materials (None entries = glTF default material).
        texture_filter: ``"trilinear" | "anisotropic" | "bilinear" | "nearest"``.
        mip_cache: a :class:`MipCache` reused across calls for constant textures.
        max_anisotropy: probes a pixel at most for ``texture_filter="anisotropic"``.
        face_object: ``(F,)`` int64 object id of each face (required for ``instance`` and
            ``semantic``).
        object_category: ``(N + 1,)`` int64 category of each object id (``semantic``).
        object_coords: ``(B, V, 3)`` or ``(V, 3)`` NOCS coordinates (``object_coords``).
        release_derivatives: drop ``frags``' barycentric derivatives once the textures are
            sampled (memory: the caller reads them no more).
        packed: requested channels among :data:`PACKABLE_CHANNELS` to return packed
            (``GBuffer.packed``, :class:`PackedChannels`, covered pixels only) instead of
            as images (memory: for channels only ``shade`` reads).

    Returns:
        A :class:`GBuffer` holding exactly the requested channels, each ``(B, C, H, W)``
        (those named in ``packed``: ``(C, N)`` in ``GBuffer.packed``).
    """
    channels = check_channels(channels)
    keep_packed = set(packed)
    if not keep_packed <= channels & PACKABLE_CHANNELS:
        raise ValueError(f"packed: {sorted(keep_packed - (channels & PACKABLE_CHANNELS))} are "
                         f"not requested channels among {sorted(PACKABLE_CHANNELS)}")
    held: dict[str, torch.Tensor] = {}

    def put(ch: str, values: torch.Tensor) -> None:
        """Channel ``ch`` from its packed ``(C, N)`` values: kept packed or as an image."""
        if ch in keep_packed:
            held[ch] = values
        else:
            out[ch] = to_image(values, frags)

    need = required_inputs(channels, materials)
    out: dict[str, torch.Tensor] = {}
    dtype = positions.dtype
    device = frags.pixels.device
    n = frags.pixels.numel()
    if "mask" in channels:
        out["mask"] = frags.mask.to(dtype)
    if "face_id" in channels:
        out["face_id"] = frags.face_id.unsqueeze(1)
    if "amodal" in channels:
        raise ValueError("channels: 'amodal' is rendered by the Renderer (one rasterization "
                         "per object), not by geometry_pass")
    out.update(_identity_channels(frags, channels, face_object, object_category))
    if "object_coords" in channels:
        if object_coords is None:
            raise ValueError("object_coords: required by the 'object_coords' channel")
        out["object_coords"] = to_image(interpolate_packed(object_coords.to(dtype), frags)[0],
                                        frags)
    if not channels - {"mask", "face_id", "object_coords"} - _IDENTITY_CHANNELS:
        return GBuffer(**out)

    uv = duv_dx = duv_dy = None
    if "uv" in need:
        if uvs is None:
            raise ValueError("uvs: required by the requested channels / textured materials")
        deriv = "uv_derivatives" in need and frags.bary_dx_packed is not None
        uv, duv_dx, duv_dy = interpolate_packed(uvs.to(dtype), frags, derivatives=deriv)
        if "uv" in channels:
            out["uv"] = to_image(uv, frags)

    # Per-pixel material index (N,); None: every pixel has material 0
    mat_index = None
    if face_material is not None and len(materials) > 1:
        face = frags.face_id.view(-1).index_select(0, frags.pixels)
        mat_index = face_material.to(frags.pixels.device).index_select(0, face)
        del face
    mats = list(materials) or [None]

    trilinear = duv_dx is not None and texture_filter == "trilinear"
    slots = [k[len("texture:"):] for k in sorted(need) if k.startswith("texture:")]
    if tangents is None:
        slots = [s for s in slots if s != "normal"]  # no normal mapping without tangents
    memo: dict[int, dict[str, torch.Tensor]] = {}

    def pick(t: torch.Tensor, sel: torch.Tensor | None) -> torch.Tensor:
        return t if sel is None else t.index_select(1, sel)  # None: all pixels, no copy

    def sample(slot: str, m: int, sel: torch.Tensor | None) -> torch.Tensor | None:
        """Sample material m's texture ``slot`` at the packed pixels ``sel`` (None: all)
        -> (C, n_sel)."""
        mat = mats[m]
        if mat is None or getattr(mat, slot + "_texture") is None:
            return None
        if trilinear:  # all of the material's textures at once (one mip atlas per size)
            if m not in memo:
                memo[m] = _sample_atlases(mat, slots, pick(uv, sel), pick(duv_dx, sel),
                                          pick(duv_dy, sel), mip_cache)
            return memo[m][slot]
        raw = getattr(mat, slot + "_texture")

        def build() -> MipTexture:
            tex = mat.texture(slot, dtype=dtype, device=device)
            if mip_cache is not None and tex.data_ptr() == raw.data_ptr():
                tex = tex.clone()  # a cached pyramid must not keep the texture alive
            return MipTexture(tex[None], address="wrap")

        mip = mip_cache.get(raw, build, dtype, device) if mip_cache is not None else build()
        grid = pick(uv, sel)[None, :, None, :]  # (1, 2, 1, n_sel)
        if duv_dx is not None and texture_filter in ("trilinear", "anisotropic"):
            ddx = pick(duv_dx, sel)[None, :, None, :]
            ddy = pick(duv_dy, sel)[None, :, None, :]
            val = mip.sample(grid, ddx, ddy, filter=texture_filter, max_anisotropy=max_anisotropy)
        else:
            val = mip.sample(grid, filter="bilinear" if texture_filter != "nearest"
                                  else "nearest")
        return val[0, :, 0]

    need_material = channels & {"albedo", "alpha", "metallic", "roughness", "ao", "emissive"}
    if need_material and mat_index is None:  # one material: its values straight to images
        values = _material_values(mats[0], need_material, lambda s: sample(s, 0, None), n,
                                  positions)
        for ch in list(values):  # a constant (C, 1) is scattered as an expanded view
            put(ch, values.pop(ch).expand(-1, n))
    elif need_material:
        sizes = {"albedo": 3, "alpha": 1, "metallic": 1, "roughness": 1, "ao": 1, "emissive": 3}
        by_material = {ch: positions.new_zeros(sizes[ch], n) for ch in need_material}
        for m in range(len(mats)):
            sel = (mat_index == m).nonzero().squeeze(1)
            if sel.numel() == 0:
                continue
            values = _material_values(mats[m], need_material, lambda s, m=m, sel=sel: sample(
                s, m, sel), sel.numel(), positions)
            for ch, v in values.items():  # in place: one packed copy per channel
                by_material[ch].index_copy_(1, sel, v.expand(-1, sel.numel()))
            del values
        for ch in need_material:
            put(ch, by_material.pop(ch))
    for values in memo.values():  # only a normal map is sampled later
        for slot in [s for s in values if s != "normal"]:
            del values[slot]
    normal_mapped = "normal" in channels and "tangent" in need and tangents is not None
    if not normal_mapped:
        uv = duv_dx = duv_dy = None
        if release_derivatives:  # the texture LOD is done: not alive at the pass's peak
            frags.bary_dx_packed = frags.bary_dy_packed = None

    # geometry after the materials: the texture lookups' temporaries (the pass's peak)
    # do not coexist with these images
    pos = interpolate_packed(positions, frags)[0] if "position" in need else None  # (3, N)
    if "position" in channels:
        put("position", pos)
    if "depth" in channels:
        rows = view.to(dtype).expand(frags.face_id.shape[0], 4, 4)[:, 2].index_select(
            0, frags.items)  # (N, 4) third row of each pixel's view matrix
        z_view = (rows[:, :3] * pos.T).sum(-1) + rows[:, 3]
        out["depth"] = to_image(-z_view[None], frags)
        del rows, z_view
    if "distance" in channels:  # |view-space point|: the ray length from the eye
        rows = view.to(dtype).expand(frags.face_id.shape[0], 4, 4)[:, :3].index_select(
            0, frags.items)  # (N, 3, 4)
        p_view = (rows[:, :, :3] * pos.T[:, None]).sum(-1) + rows[:, :, 3]  # (N, 3)
        out["distance"] = to_image(_norm_rows(p_view)[None], frags)
        del rows, p_view
    del pos  # memory: packed copies of channels never coexist with all their images

    if "normal" in channels:
        if normals is None:
            raise ValueError("normals: vertex normals are required for the 'normal' channel")
        nrm = interpolate_packed(normals.to(dtype), frags)[0]  # (3, N)
        if normal_mapped:
            tan = interpolate_packed(tangents.to(dtype), frags)[0]  # (4, N)
            if mat_index is None:
                mat_index = torch.zeros(n, dtype=torch.long, device=device)
            nrm = _apply_normal_maps(nrm, tan, mats, mat_index, sample)
            del tan
        in_place = not torch.is_grad_enabled()  # memory: no packed copies at the peak
        nrm = safe_normalize(nrm, dim=0, inplace=in_place)
        if frags.front_facing is not None:  # back faces are seen from behind: flip
            # x * -1 is -x bit for bit (one (1, N) sign, no negated (3, N) copy: memory)
            sign = torch.where(frags.front_facing, 1.0, -1.0).to(nrm.dtype)[None]
            nrm = nrm.mul_(sign) if in_place else nrm * sign
        put("normal", nrm)
    return GBuffer(**out, packed=PackedChannels(frags.pixels, held) if held else None)


def _identity_channels(frags: Fragments, channels: set[str], face_object: torch.Tensor | None,
                       object_category: torch.Tensor | None) -> dict[str, torch.Tensor]:
    """``instance`` / ``semantic`` ``(B, 1, H, W)`` int64 of the visible faces (0 empty)."""
    wanted = channels & _IDENTITY_CHANNELS
    if not wanted:
        return {}
    if face_object is None:
        raise ValueError(f"face_object: required by the {sorted(wanted)} channel(s)")
    if "semantic" in wanted and object_category is None:
        raise ValueError("object_category: required by the 'semantic' channel")
    device = frags.pixels.device
    face = frags.face_id.view(-1).index_select(0, frags.pixels)
    inst = face_object.to(device=device, dtype=torch.int64).index_select(0, face)
    out = {}
    if "instance" in wanted:
        out["instance"] = to_image(inst[None], frags, fill=0)
    if "semantic" in wanted:
        cat = object_category.to(device=device, dtype=torch.int64).index_select(0, inst)
        out["semantic"] = to_image(cat[None], frags, fill=0)
    return out


def _norm_rows(v: torch.Tensor) -> torch.Tensor:
    """Euclidean norm of the rows of ``v`` ``(N, 3)`` -> ``(N,)``, with a zero (not NaN)
    gradient at the zero vector."""
    len2 = (v * v).sum(-1)
    ok = len2 > 0
    return torch.where(ok, torch.where(ok, len2, torch.ones_like(len2)).sqrt(),
                       torch.zeros_like(len2))


def _sample_atlases(mat: Material, slots: list[str], uv: torch.Tensor, duv_dx: torch.Tensor,
                    duv_dy: torch.Tensor, mip_cache: MipCache | None) -> dict[str, torch.Tensor]:
    """Trilinear lookups of the material's textures in ``slots`` at ``uv`` ``(2, N)``:
    ``{slot: (C, N)}``. Textures of one size are stacked in one :class:`MipAtlas` (kept in
    ``mip_cache``), so the material costs one lookup per texture size."""
    dtype, device = uv.dtype, uv.device
    groups: dict[tuple[int, int], list[str]] = {}
    for slot in slots:
        raw = getattr(mat, slot + "_texture")
        if raw is not None:
            groups.setdefault(tuple(raw.shape[-2:]), []).append(slot)
    out: dict[str, torch.Tensor] = {}
    for group in groups.values():
        def build(group=group) -> MipAtlas:
            return MipAtlas([mat.texture(s, dtype=dtype, device=device) for s in group],
                            address="wrap")

        raws = tuple(getattr(mat, s + "_texture") for s in group)
        atlas = mip_cache.get(raws, build, dtype, device) if mip_cache is not None else build()
        values = atlas.sample(uv, duv_dx, duv_dy).split(atlas.channels, 0)
        out.update(zip(group, values, strict=True))
    return out


def _factor(value, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(value, dtype=like.dtype, device=like.device)


def _material_values(mat: Material | None, channels: set[str], sample, n: int,
                     like: torch.Tensor) -> dict[str, torch.Tensor]:
    """glTF metallic-roughness values of one material at its pixels, each (C, n) or (C, 1)."""
    mat = mat if mat is not None else Material()
    out = {}
    if channels & {"albedo", "alpha"}:
        base = _factor(mat.base_color_factor, like).reshape(4, 1)
        tex = sample("base_color")
        if tex is not None and "alpha" not in channels:  # (3, n): no alpha row kept alive
            base = base[:3] * tex[:3]
        elif tex is not None:
            if tex.shape[0] == 3:
                tex = torch.cat([tex, torch.ones_like(tex[:1])])
            base = base * tex
        out["albedo"], out["alpha"] = base[:3], base[3:4]
    if channels & {"metallic", "roughness"}:
        metallic = _factor(mat.metallic_factor, like).reshape(1, 1)
        roughness = _factor(mat.roughness_factor, like).reshape(1, 1)
        tex = sample("metallic_roughness")
        if tex is not None:
            roughness = roughness * tex[1:2]
            metallic = metallic * tex[2:3]
        out["metallic"], out["roughness"] = metallic, roughness
    if "ao" in channels:
        tex = sample("occlusion")
        ao = like.new_ones(1, 1)
        if tex is not None:
            ao = 1.0 + mat.occlusion_strength * (tex[:1] - 1.0)
        out["ao"] = ao
    if "emissive" in channels:
        emissive = _factor(mat.emissive_factor, like).reshape(3, 1)
        tex = sample("emissive")
        out["emissive"] = emissive * tex[:3] if tex is not None else emissive
    return {k: v for k, v in out.items() if k in channels}


def _apply_normal_maps(nrm, tan, mats, mat_index, sample) -> torch.Tensor:
    """Perturb interpolated normals (3, N) by each material's tangent-space normal map.

    glTF: n' = normalize(T x + B y + N z) with (x, y, z) = (2 tex - 1) * (scale, scale, 1)
    and B = w (N x T) (w = tangent handedness).
    """
    n_geo = safe_normalize(nrm, dim=0)
    # Gram-Schmidt: the tangent made orthogonal to the interpolated normal
    t = safe_normalize(tan[:3] - (tan[:3] * n_geo).sum(0, keepdim=True) * n_geo, dim=0)
    bit = torch.linalg.cross(n_geo, t, dim=0) * torch.where(tan[3:4] < 0, -1.0, 1.0)
    out = nrm
    for m, mat in enumerate(mats):
        if mat is None or mat.normal_texture is None:
            continue
        sel = (mat_index == m).nonzero().squeeze(1)
        if sel.numel() == 0:
            continue
        tex = sample("normal", m, sel)
        xyz = tex[:3] * 2.0 - 1.0
        xyz = xyz * xyz.new_tensor([mat.normal_scale, mat.normal_scale, 1.0])[:, None]
        mapped = (t.index_select(1, sel) * xyz[0:1] + bit.index_select(1, sel) * xyz[1:2]
                  + n_geo.index_select(1, sel) * xyz[2:3])
        out = out.index_copy(1, sel, mapped)
    return out


def _sign_not_zero(v: torch.Tensor) -> torch.Tensor:
    return torch.where(v >= 0, 1.0, -1.0).to(v.dtype)


def encode_octahedral(normal: torch.Tensor) -> torch.Tensor:
    """Unit normals (B, 3, H, W) -> 2-channel octahedral code (B, 2, H, W) in [-1, 1]
    (Cigolle et al. 2014, "A Survey of Efficient Representations for Independent Unit
    Vectors"): compact G-buffer storage, e.g. as float16 or 2 x 16-bit. Zero normals map
    to (0, 0)."""
    l1 = normal.abs().sum(1, keepdim=True)
    p = normal[:, :2] / torch.where(l1 > 0, l1, torch.ones_like(l1))
    folded = (1 - p.flip(1).abs()) * _sign_not_zero(p)
    return torch.where(normal[:, 2:3] < 0, folded, p)


def decode_octahedral(code: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`encode_octahedral`: (B, 2, H, W) -> unit normals (B, 3, H, W)."""
    z = 1 - code.abs().sum(1, keepdim=True)
    xy = torch.where(z < 0, (1 - code.flip(1).abs()) * _sign_not_zero(code), code)
    return safe_normalize(torch.cat([xy, z], dim=1), dim=1)
