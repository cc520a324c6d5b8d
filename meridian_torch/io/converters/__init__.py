"""Converters from other recordings to the sequence folder format (README, Formats), one module per
source; `meridian-torch convert SOURCE` runs them. Each streams frames into
`io.sequence.SequenceWriter`, so memory stays bounded and the output folder appears only when
complete."""
