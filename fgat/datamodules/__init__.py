"""Lightning DataModules: simulated phantoms and measured FLFM data."""

from fgat.datamodules.flfm import FLFMDataModule
from fgat.datamodules.phantom import PhantomDataModule
from fgat.datamodules.scene import FLFMScene

__all__ = ["FLFMDataModule", "FLFMScene", "PhantomDataModule"]
