"""LightningModules of the two 4DGAT stages."""

from fgat.modules.dynamic import DynamicModule
from fgat.modules.static import StaticModule

__all__ = ["DynamicModule", "StaticModule"]
