"""Indoor navigation: procedural grid layouts, batched geodesic fields and depth ray casting, the PointNav env."""

from torchsim.envs.nav.pointnav import PointNav

__all__ = ["PointNav"]
