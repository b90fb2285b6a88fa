"""hostd: a host daemon for g2core CNC and laser controllers."""

__version__ = "0.1.0"
