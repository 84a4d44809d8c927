"""Batched camera rendering in torch: depth, geom-id segmentation and RGB images of every env at once.

    from torchsim.render import Camera, Scene, render
    scene = Scene.build(mj_model, system)                  # once per model: geoms, colours, cameras
    cam = Camera.look_at(eye=(3, -3, 2), target=(0, 0, 0.5))
    images = render(scene, state, cam, 64, 64, rgb=True)   # images.depth (B, 64, 64), images.rgb (B, 64, 64, 3)

Modules: ``scene`` (the static geom table and cameras), ``camera`` (camera poses and pixel rays), ``raycast``
(closed-form ray-shape hits), ``mesh`` (triangle meshes: a BVH per mesh asset and its batched traversal),
``nearest`` (nearest hits: dense or culled by screen tiles), ``renderer`` (the entry point ``render``), ``frames``
(rotation helpers). ``docs/rendering.md`` has the conventions and the measured
agreement with MuJoCo's renderer.
"""

from torchsim.render.camera import Camera
from torchsim.render.renderer import Images, render
from torchsim.render.scene import Scene, UnsupportedGeomError

__all__ = ["Camera", "Images", "Scene", "UnsupportedGeomError", "render"]
