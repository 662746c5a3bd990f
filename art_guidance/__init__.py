"""art_guidance: onboard rendezvous guidance (ART warm start, post hoc check, robust SCP)."""

__version__ = "0.1.0"
