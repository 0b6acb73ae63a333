"""Analyses built on retinal images (above :mod:`lfsim.render`, which stays a renderer).

* :mod:`.psf`: the retinal point-spread function of a point shown by the display at a
  depth, or of the real point in the natural view (``lfsim psf``).
"""
