"""Rendering with Mitsuba 3: the LLVM backend and variant (``backend``), scene files with their
includes inlined and a box filter with a float32 film forced (``scene_io``), renders at a given spp,
seed and resolution, in two halves or with AOVs (``render``), and renders in crops under a memory
bound (``render_crops``). Uses only :mod:`imaging`."""