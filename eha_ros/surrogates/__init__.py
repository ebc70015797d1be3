"""Fast surrogates of the valve's fluid-dynamic block (chapter 5 of the reference) as the plant
runs them: lookup table, genetic-algorithm function, neural networks, and the dynamic family
that learns the metering edges only.  :mod:`.registry` lists the kinds and loads artefacts.

Inference only: numpy and numba, no torch; their builds are :mod:`eha_ros.training`.
"""
