"""ncore-convert: public autonomous-driving datasets to NVIDIA NCore V4.

Importing the package imports nothing else: the console script (:mod:`ncore_convert.entry`)
installs its stop handlers before any other module loads. ``__version__`` is looked up on first use.
"""


def __getattr__(name: str) -> str:
    if name != "__version__":
        raise AttributeError(f"module 'ncore_convert' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("ncore-convert")
    except PackageNotFoundError:  # running from a source tree without installation
        found = "0+unknown"
    globals()["__version__"] = found
    return found
