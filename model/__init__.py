"""The networks and what describes them: ``config`` (ModelConfig and the architecture presets),
``network`` (the paper's flat dense network and a plain CNN), ``unet`` (the multi-scale dense
network with an optional predicted filter), ``architectures`` (build, radius, alignment, memory),
``device`` (the one place ``--device`` is resolved), ``transfer`` (radiance <-> network space),
``noise_input`` (the noise channels of a two-halves render), ``grow`` (a trained network made
deeper), ``checkpoint`` (self-describing safetensors files and their cards' record) and
``registry`` (the shipped models by name, their cards). Uses only :mod:`imaging`.
"""
