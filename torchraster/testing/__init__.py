"""Independent float64 references for tests and benchmarks (docs/design.md, layer 3).

Nothing here imports the engine: each reference re-derives what it checks from the public
contract, so a test comparing the engine to a reference compares two independent
implementations.

* :mod:`torchraster.testing.reference_raster`: a brute-force rasterizer (every pixel
  against every face, 2-D homogeneous edge functions, no clipping code), reference
  interpolation, float64 camera matrices and hostile random scenes;
* :mod:`torchraster.testing.reference_brdf`: GGX (Walter 2007), height-correlated Smith
  (Heitz 2014) and a hemisphere quadrature of any BRDF;
* :mod:`torchraster.testing.reference_texture`: the exact box-filtered checkerboard on a
  steep plane (closed-form integration along lines), for texture filtering;
* :mod:`torchraster.testing.reference_fog`: a brute-force single-scattering fog march with
  numerically integrated transmittance, and the Henyey-Greenstein phase written out;
* :mod:`torchraster.testing.llvmpipe`: Mesa's llvmpipe (OpenGL on the CPU through moderngl)
  behind the same clip-space contract; optional, ``available()`` says whether it runs here.

Import the submodules explicitly (``from torchraster.testing import reference_raster``);
importing this package imports none of them.
"""
