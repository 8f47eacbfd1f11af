"""Bad input to rasterize / interpolate: one clear ValueError / TypeError naming the argument.

Decided from a user's view: a mesh with 0 faces renders an empty image (not an error); faces
that index vertices which do not exist (including any face with 0 vertices) are an error.
"""

from __future__ import annotations

import pytest
import torch

import torchraster as tr

CLIP = torch.tensor([[[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0]]])
FACES = torch.tensor([[0, 1, 2]])
RES = (8, 8)


def _raises(name: str, fn, *args, **kwargs) -> None:
    with pytest.raises((ValueError, TypeError), match=rf"\b{name}\b"):
        fn(*args, **kwargs)


def _nan_clip() -> torch.Tensor:
    c = CLIP.clone()
    c[0, 1, 0] = float("nan")
    return c


def _inf_clip() -> torch.Tensor:
    c = CLIP.clone()
    c[0, 2, 3] = float("inf")
    return c


BAD_CLIP = {
    "list": CLIP.tolist(),
    "no_batch": CLIP[0],
    "xyz_only": CLIP[..., :3],
    "5_coords": torch.cat([CLIP, CLIP[..., :1]], -1),
    "int": CLIP.long(),
    "nan": _nan_clip(),
    "inf": _inf_clip(),
}


@pytest.mark.parametrize("case", list(BAD_CLIP))
def test_bad_clip_pos(case: str) -> None:
    _raises("clip_pos", tr.rasterize, BAD_CLIP[case], FACES, resolution=RES)


BAD_FACES = {
    "list": [[0, 1, 2]],
    "float": FACES.float(),
    "quads": torch.tensor([[0, 1, 2, 0]]),
    "flat": torch.tensor([0, 1, 2]),
    "out_of_range": torch.tensor([[0, 1, 3]]),
    "negative": torch.tensor([[0, -1, 2]]),
}


@pytest.mark.parametrize("case", list(BAD_FACES))
def test_bad_faces(case: str) -> None:
    _raises("faces", tr.rasterize, CLIP, BAD_FACES[case], resolution=RES)


def test_faces_without_vertices() -> None:
    _raises("faces", tr.rasterize, CLIP[:, :0], FACES, resolution=RES)


@pytest.mark.parametrize(
    "res", [0, (0, 8), (8, 0), (-4, 8), (8,), (8, 8, 8), (8.5, 8), "8x8", None]
)
def test_bad_resolution(res: object) -> None:
    _raises("resolution", tr.rasterize, CLIP, FACES, resolution=res)


@pytest.mark.parametrize(
    "ranges",
    [
        torch.tensor([0, 1]),  # not (B, 2)
        torch.tensor([[0, 1], [0, 1]]),  # B = 2 rows for B = 1
        torch.tensor([[0.0, 1.0]]),  # float
        torch.tensor([[0, 2]]),  # end > F
        torch.tensor([[1, 0]]),  # start > end
        torch.tensor([[-1, 1]]),
    ],
)
def test_bad_face_ranges(ranges: torch.Tensor) -> None:
    _raises("face_ranges", tr.rasterize, CLIP, FACES, resolution=RES, face_ranges=ranges)


@pytest.mark.parametrize("n_vert", [0, 3])
def test_zero_faces_render_empty(n_vert: int) -> None:
    frags = tr.rasterize(CLIP[:, :n_vert].repeat(2, 1, 1), FACES[:0], resolution=(4, 6))
    assert frags.face_id.shape == (2, 4, 6) and (frags.face_id == -1).all()
    assert frags.bary.shape == (2, 4, 6, 3) and (frags.bary == 0).all()
    assert frags.depth.shape == (2, 4, 6) and torch.isinf(frags.depth).all()
    img = tr.interpolate(torch.zeros(2, n_vert, 5), frags, FACES[:0])
    assert img.shape == (2, 5, 4, 6) and (img == 0).all()


def test_empty_face_range_renders_empty_item() -> None:
    frags = tr.rasterize(CLIP.repeat(2, 1, 1), FACES, resolution=RES,
                         face_ranges=torch.tensor([[0, 1], [1, 1]]))
    assert (frags.face_id[0] >= 0).any() and (frags.face_id[1] == -1).all()


def _frags():
    return tr.rasterize(CLIP, FACES, resolution=RES)


@pytest.mark.parametrize(
    "attrs",
    [
        torch.zeros(3),  # 1-D
        torch.zeros(1, 2, 4),  # fewer vertices than the faces use
        torch.zeros(3, 4, dtype=torch.int64),  # integer
        torch.zeros(3, 1, 3, 4),  # 4-D
        torch.zeros(2, 3, 4),  # batch 2 for fragments of batch 1
        [[0.0, 0.0, 0.0]] * 3,  # not a tensor
    ],
)
def test_bad_vertex_attrs(attrs: object) -> None:
    _raises("vertex_attrs", tr.interpolate, attrs, _frags(), FACES)


def test_interpolate_bad_frags_and_faces() -> None:
    _raises("frags", tr.interpolate, torch.zeros(3, 2), "fragments", FACES)
    _raises("faces", tr.interpolate, torch.zeros(3, 2), _frags(), FACES.float())
    _raises("faces", tr.interpolate, torch.zeros(3, 2), _frags(), torch.tensor([0, 1, 2]))


def test_float64_input_gives_float64_output() -> None:
    frags = tr.rasterize(CLIP.double(), FACES, resolution=RES)
    assert frags.bary.dtype == torch.float64 and frags.depth.dtype == torch.float64
    img = tr.interpolate(torch.rand(3, 2, dtype=torch.float64), frags, FACES)
    assert img.dtype == torch.float64
