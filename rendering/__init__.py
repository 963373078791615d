"""Rendering with Mitsuba 3: the LLVM backend and variant (``backend``), scene files with their
includes inlined and a box filter with a float32 film forced (``scene_io``), renders at a given spp,
seed and resolution, in two halves or with AOVs (``render``), renders in crops under a memory
bound (``render_crops``), and the sensor's frame that normals turn into (``camera``). Uses only :mod:`imaging`."""