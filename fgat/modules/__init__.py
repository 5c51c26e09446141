"""LightningModules of the two 4DGAT stages: thin shells over :mod:`fgat.reconstruction`."""

from fgat.modules.dynamic import DynamicModule
from fgat.modules.static import StaticModule

__all__ = ["DynamicModule", "StaticModule"]
