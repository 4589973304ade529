"""The science of the host: shape estimation and tactile analysis.

Pure computation on arrays — no transports, no threads, no simulator. These modules import only
`protocol.lattice` (addressing and joint normals) and each other, so a recording, a live session and
a test all call the same code. `host.estimator` is kept as an alias of `host.analysis.estimator`.
"""
