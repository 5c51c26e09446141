"""Lightning DataModules: simulated phantoms and measured FLFM data."""

from fgat.datamodules.flfm import FLFMDataModule
from fgat.datamodules.phantom import PhantomDataModule

__all__ = ["FLFMDataModule", "PhantomDataModule"]
