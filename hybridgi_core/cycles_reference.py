"""The Cycles settings HybridGI is measured against, in one place: the CLI's reference renders,
the add-on's Compare with Cycles operator and the time-to-quality benchmark all set these.

Converged diffuse transport without the defaults' bias (4 diffuse bounces, indirect clamped at
10), and no denoiser or adaptive sampling to hide the reference's own noise level. Plain data:
names of `scene.cycles` properties and their values.
"""

CYCLES_REFERENCE = {
    "device": "CPU",
    "use_denoising": False,
    "use_adaptive_sampling": False,
    "max_bounces": 32,
    "diffuse_bounces": 32,
    "sample_clamp_direct": 0.0,
    "sample_clamp_indirect": 0.0,
}
