"""Optics: PSF banks and shift-variant PSF operators."""
