"""Analyses built on retinal images (above :mod:`lfsim.render`, which stays a renderer).

* :mod:`.psf`: the retinal point-spread function of a point shown by the display at a
  depth, or of the real point in the natural view (``lfsim psf``).
* :mod:`.accommodation`: the predicted accommodation response to points shown at depths,
  on the display path and in the natural view (``lfsim accommodation``).
* :mod:`.focus_cues`: the focus-cue analysis of a focal stack (the paper's Fig. 9), run
  by ``lfsim focal-stack``.
"""
