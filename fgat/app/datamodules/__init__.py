"""Lightning DataModules: simulated phantoms and measured FLFM data."""

from fgat.app.datamodules.flfm import FLFMDataModule
from fgat.app.datamodules.phantom import PhantomDataModule

__all__ = ["FLFMDataModule", "PhantomDataModule"]
