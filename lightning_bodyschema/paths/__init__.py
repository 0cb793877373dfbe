"""Geometric muscle paths: MuJoCo's spatial-tendon path topology (which bodies a muscle's sites ride, which
wrapping spheres and cylinders it may wrap, with which side sites) with fitted numbers (site positions, wrapping
geoms' centres and radii, side sites), evaluated in torch. Never imports Lightning.

``parts``: a path's topology and its numbers as MuJoCo's model holds them.
``layout``, ``module``: ``path_layout(model)``, the paths on the moving frames; ``GeometricPath``, lengths and arms.
``wrap``: MuJoCo 4.0's wrap of one segment around a sphere or cylinder (side sites, inside wrap), batched in torch.
"""
