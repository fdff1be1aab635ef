"""tryon: an online 3D clothes try-on service (body model, avatars, GLB export)."""

__version__ = "0.1.0"
