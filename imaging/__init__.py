"""The foundation every other package builds on: errors (``errors``), atomic writes and strict JSON
(``atomic_io``), image files (``exr``, ``exr_layers``, ``bitmap_io``: PFM/HDR, ``png``), dataset
file names (``naming``), metrics (``metrics``), file hashes (``hashing``), row blocks and threads
for whole-image passes (``blocks``) and the process's peak memory (``peak_rss``). It imports no
other package of this project (tests/test_layers.py)."""
