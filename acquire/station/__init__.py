"""The plant's station: the archive of every cell's finished runs, each robot's calibration
history and state, the service that pulls runs from the cells, and the fleet view.

``archive``  files of a finished run stored by robot serial and date, sha256-verified, resumable,
             never replaced, within size limits and a free-space reserve
``scrub``    the archive read back against its manifests; bad copies quarantined, fetched again
``history``  per robot: every calibration's offsets (± σ) and accuracy before/after
``drift``    a new measurement's offsets against the robot's entered calibration (χ² test)
``states``   what an engineer acts on: calibrated, drifted, out of tolerance, never calibrated, check due
``intake``   a run archived → its history entry, verdicts recomputed
``service``  ``acquire station``: discover cells, pull concurrently, verify, store, confirm, repair
``alerts``   a command and/or webhook told of state changes, damaged copies, refused runs
``router``   ``acquire router``: the site's Zenoh router where no zenohd runs
``fleet``    ``acquire fleet``: the table, the index and per-robot HTML pages
``config``   the station's configuration file
"""
