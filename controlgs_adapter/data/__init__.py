"""Assets shipped with the package (PSF bank, built-in scene backbone)."""
