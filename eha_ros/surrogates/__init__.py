"""Fast surrogates of the valve's fluid-dynamic block and the wear diagnosis (chapter 5 of the
reference): map databases, lookup table, genetic-algorithm function, neural networks.

Built on :mod:`eha_ros.physics`; torch is used for training only.
"""
