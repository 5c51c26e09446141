"""The Lightning DataModules under the name configs use
(``data.class_path: fgat.datamodules.FLFMDataModule``); the code lives in
:mod:`fgat.app.datamodules`."""

from fgat.app.datamodules import (  # noqa: F401
    FLFMDataModule,
    PhantomDataModule,
)

__all__ = [
    "FLFMDataModule",
    "PhantomDataModule",
]
