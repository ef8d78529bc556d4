"""Readers (and the .splat writer) for splat formats other than the standard 3DGS PLY.

Each reader validates a file before trusting it: sizes against the file length, counts capped by the file
size before anything is allocated, reserved fields and versions, and decompressed sizes capped by what the
declared count implies. Every problem is an InputError naming the file, the field and what was expected.
Field mappings and what each format loses are documented in format_spec/foreign_formats.md. What every reader shares
(the memory budget, regular-file reads, opacity logits) is splatstream/reader_support.py, which ply.py uses too.
"""
