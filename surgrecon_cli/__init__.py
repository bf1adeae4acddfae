"""surgrecon: multi-camera 3D reconstruction of dynamic surgical cavities.

Data flow (Su, Huang & Hannaford, IROS 2019, Fig. 2):
ingest -> template -> target -> registration -> classification -> report.
"""

__version__ = "0.1.0"
