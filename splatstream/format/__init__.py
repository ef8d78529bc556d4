"""Everything about the scene format (format_spec/format.md), in one place the encoder, decoder, server, renderer
and streaming client all import: nothing else re-derives a byte layout or a file name.

names      file names and URLs of a scene          layout     Morton order, chunks, texture layout
texformats texel bit layouts                        planes     planes and payload groups
codec      quantisation of attributes into planes   container  payload files (zstd, sections)
manifest   the typed, validated manifest            presets    preset names -> texel formats
decode     payload bytes -> planes / values / Gaussians
"""
