"""Rendering maps into cameras: mesh ray casting, surfel and point splatting."""
