"""The positioning-uncertainty sweep and its variants.

`problem` builds the work every variant shares; `in_memory` runs it with every node in memory,
`pieces` keeps only per-node summaries, `slabs` streams maps larger than memory, `resume` keeps
finished chunks on disk, `distributed` runs chunks on Dask workers. The same seed gives the same
numbers in every variant.
"""
