"""LightningModules of the two 4DGAT stages: thin shells over :mod:`fgat.recon`."""

from fgat.app.modules.dynamic import DynamicModule
from fgat.app.modules.static import StaticModule

__all__ = ["DynamicModule", "StaticModule"]
