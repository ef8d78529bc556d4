"""The GPU shell of `encode --lod-refine` (lod.md 6, the optional step): torch + gsplat, an optional extra
(`pip install 'splatstream[refine]'`, a CUDA GPU). The core (splatstream/) never imports it: the CLI hands its
refiner to the encoder (EncodeOptions.lod_refiner)."""
