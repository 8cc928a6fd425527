"""kgs_app: the `kgs-app` command line and the desktop viewer."""
