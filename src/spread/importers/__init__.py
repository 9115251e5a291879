"""Importers: other dataset layouts → the platform's dataset folder (``spread-import``).

Modules: ``base`` (room references, asset requests, the source interface, tag checks), one module per
source layout (``spread_release``: the SPREAD authors' processed ProcTHOR; ``threed_front``:
InstructScene's preprocessed 3D-FRONT), ``run`` (the parallel, resumable driver and the manifest).
"""
