"""The CPU shell of `encode --lod-refine cpu` (lod.md 6, the optional step): numba, the `fast` extra
(`pip install 'splatstream[fast]'`), no GPU. The core (splatstream/) never imports it: the CLI hands its refiner to
the encoder (EncodeOptions.lod_refiner)."""
