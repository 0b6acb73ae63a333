"""The InI-HMD model: first-order design equations (Eqs. 1–10 of the method)."""

from .first_order import IniFirstOrder, ini_first_order

__all__ = ["IniFirstOrder", "ini_first_order"]
