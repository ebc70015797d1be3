"""Health diagnosis of the servovalve (chapter 5.4 of the reference and beyond): the in-service
posterior over wear, the valve-test and pre-flight estimators, the monitor core that runs them
on the recorded states, and the thresholds that grade them.  Their artefacts ship in
``models/``; their builds are :mod:`eha_ros.training`.  No ROS, no torch.
"""
