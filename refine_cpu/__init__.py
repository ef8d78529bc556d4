"""The CPU shell of `encode --lod-refine cpu` (lod.md 6, the optional step): numba, the `fast` extra
(`pip install 'splatstream[fast]'`), no GPU. The core (splatstream/) never imports it: the CLI hands its refiner to
the encoder (EncodeOptions.lod_refiner)."""

# The CPU fit's defaults (BENCHMARKS.md, "Refining the merged levels on the CPU"), here where the CLI's help reads
# them without importing numba.
ITERATIONS = 60  # full-batch Adam steps per level
SIZE_PX = 256
TRAINING_CAMERAS = 32
VALIDATION_CAMERAS = 16
