"""Design metrics of an InI-HMD: RMS spot, MTF and contrast at Nyquist, GD (Eq. 11),
PA (Eq. 12), local distortion, footprints. Plain functions on numpy arrays."""

from .distortion import gd_deg, local_distortion
from .footprint import pa
from .image import psnr, ssim
from .mtf import diffraction_mtf, geometric_mtf
from .pupil import gauss_legendre_square, mtf_grid, perimeter
from .spot import angular_offsets, retinal_tan, rms_spot

__all__ = ["angular_offsets", "diffraction_mtf", "gauss_legendre_square", "gd_deg", "geometric_mtf",
           "local_distortion", "mtf_grid", "pa", "perimeter", "psnr", "retinal_tan", "rms_spot", "ssim"]
