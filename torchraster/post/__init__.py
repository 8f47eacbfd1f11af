"""Post-processing on (B, C, H, W) linear HDR tensors: DOF, bloom, exposure, tone mapping,
sRGB encoding (chained by :class:`PostChain`), SSAO (an input to the lighting pass) and
screen-space reflections (:class:`SSR`, on the lit image and its G-buffer).

Every effect is a differentiable ``torch.nn.Module``; ``enabled=False`` makes it an
identity that returns its input object without doing any work.
"""

from .bloom import Bloom, bloom_levels, bright_pass, downsample13, upsample_tent
from .blur import GaussianBlur, gaussian_blur, gaussian_kernel1d, separable_filter
from .chain import PostChain
from .dof import DepthOfField, circle_of_confusion, depth_of_field
from .exposure import AutoExposure, luminance, metered_log2_luminance
from .ssao import SSAO, projection_to_intrinsics, ssao
from .ssr import SSR, SSRMaps, trace_reflections
from .tonemap import CURVES, EncodeSRGB, Exposure, ToneMap, encode_srgb, tone_curve

__all__ = [
    "CURVES", "SSAO", "SSR", "AutoExposure", "Bloom",
    "DepthOfField", "EncodeSRGB", "Exposure",
    "GaussianBlur", "PostChain", "ToneMap",
    "bloom_levels", "bright_pass", "circle_of_confusion", "depth_of_field",
    "downsample13", "encode_srgb", "gaussian_blur", "gaussian_kernel1d", "luminance",
    "metered_log2_luminance", "projection_to_intrinsics", "separable_filter", "ssao",
    "tone_curve", "trace_reflections", "upsample_tent", "SSRMaps",
]
