"""The benchmarks' data: the sources registry, resumable verified downloads, the data home, `add` of a
copy the user has, and dataset=3dmatch|3dlomatch|kitti's choice of front end (docs/data.md)."""
