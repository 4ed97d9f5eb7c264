"""Implicit learning map (ILM): Mip-NeRF per cluster of reference cameras.

Modules:

- ``config``    NerfConfig and the named configs ``paper``, ``cpu-small``, ``test``
- ``mipnerf``   the math as pure functions (cones, frustum Gaussians, IPE, rendering,
                hierarchical resampling)
- ``model``     the flax MLP, ``Field`` (one cluster's NeRF with its normalisation) and
                ``render_rays`` / ``render_rays_narrow`` for world-frame cone rays
- ``data``      Scene -> near/far priors, normalisation, device-resident ray bank
- ``clusters``  K-means++ on camera centres with shared border images
- ``train``     vmapped, sharded, jitted training step; loop with orbax checkpoints
- ``ilm``       the ILM pytree and its map file (save/load with a format version)
- ``render``    full-view rendering, PSNR, SSIM, side-by-side PNGs
- ``toy``       a tiny analytically rendered scene for tests and demos
"""
