"""probecal application layer: the command line and the viser console, thin over ``core``."""
