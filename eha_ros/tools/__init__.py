"""Command-line tools of eha_ros."""
