"""``generate-dataset``: procedural scenes rendered at several spp with high-spp references, as a
resumable job per scene (``generate``, ``jobs``), its typed config (``config``), the dataset's
manifest (``manifest``), Dask submission to a cluster (``cluster``), the code version a worker must
match (``code_version``), a contact sheet (``preview``) and the command (``cli``). Uses
:mod:`scenes`, :mod:`rendering`, :mod:`imaging` and :mod:`console`."""
