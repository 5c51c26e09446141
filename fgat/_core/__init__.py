"""The bottom layer: validation helpers, conventions (view order, depth axis), devices,
thread pools and machine resources. Importable before torch (``fgat.__init__`` configures
the thread pools from here)."""
