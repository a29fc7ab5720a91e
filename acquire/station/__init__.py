"""The plant's station: the archive of every cell's finished runs, each robot's calibration
history and its drift check, the service that pulls runs from the cells, and the fleet view.

``archive``  files of a finished run stored by robot serial and date, sha256-verified, resumable
``history``  per robot: every calibration's offsets (± σ) and accuracy before/after
``drift``    a new measurement against the robot's last entered calibration (χ² test)
``service``  ``acquire station``: discover cells, pull, verify, store, confirm
``fleet``    ``acquire fleet``: the table and the per-robot HTML pages
"""
