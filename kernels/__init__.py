"""Warp kernels of the ssgwarp rasterizer, one module per stage.

- :mod:`.types`: the float32/float64 vector and matrix types a kernel family is built for.
- :mod:`.pixel`: the per-pixel maths (Gaussian weight, alpha gating) shared by
  the blending forward and backward passes.
- :mod:`.projection`: EWA projection, 3D/2D covariance, conic, radii, depth, culling.
- :mod:`.projection_backward`: its hand-written backward (gradients to means, quaternions,
  scales, opacities and view matrices).
- :mod:`.sh`: spherical-harmonics colour up to degree 3.
- :mod:`.binning`: tiles per Gaussian, 64-bit keys camera|tile|depth, per-tile ranges.
- :mod:`.blend_forward` / :mod:`.blend_backward`: front-to-back blending of any
  number of channels and its hand-written reverse traversal.
- :mod:`.block`: warp/block votes and warp-wide gradient sums (native CUDA snippets).
- :mod:`.fmath`: fused multiply-add, unfused add and reciprocal square root with a
  fixed rounding (so results do not depend on the compiler's contraction choices).
- :mod:`.validate`: input value checks in one pass.
- :mod:`.ssim`: the 3DGS photometric loss (L1 + D-SSIM) fused, with its hand-written backward.
- :mod:`.stats`: the densification statistics of a render, accumulated per Gaussian.
- :mod:`.probe`: a small kernel the launch layer's self-test runs both ways (ssgwarp/raster/private_api.py).

Every kernel family is built by a factory for one scalar type (``wp.float32``
or ``wp.float64``), so the same source serves both precisions. The projection's and
blending's backward passes are written by hand (Warp's generated adjoint of the projection
stays as the tests' yardstick); the SH colour's is Warp's for one camera, written by hand for
coefficients shared by several.
"""
