"""The LightningModules of the two 4DGAT stages under the name configs use
(``model.class_path: fgat.modules.StaticModule``); the code lives in :mod:`fgat.app.modules`."""

from fgat.app.modules import (  # noqa: F401
    DynamicModule,
    StaticModule,
)

__all__ = [
    "DynamicModule",
    "StaticModule",
]
