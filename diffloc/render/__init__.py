"""Rendering maps into cameras: mesh ray casting, surfel and point splatting.

- :mod:`~diffloc.render.surfel_render`: hard surfel splatting (global surfel index maps), made
  of :mod:`~diffloc.render.surfel_cull`, :mod:`~diffloc.render.surfel_windows`,
  :mod:`~diffloc.render.surfel_conics`, :mod:`~diffloc.render.surfel_raster` and
  :mod:`~diffloc.render.pixel_mask`;
- :mod:`~diffloc.render.point_render`: hard RGB-D point splatting with the sizes of
  :mod:`~diffloc.render.point_sizes`; both hard renderers share
  :mod:`~diffloc.render.zbuffer` and :mod:`~diffloc.render.view`;
- :mod:`~diffloc.render.soft_splat`: differentiable Gaussian point splatting;
- :mod:`~diffloc.render.raycast` and :mod:`~diffloc.render.texture`: textured mesh ray casting;
- :mod:`~diffloc.render._reference`: slow pure-torch twins of the renderers, for tests.
"""
