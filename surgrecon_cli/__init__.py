"""surgrecon: multi-camera 3D reconstruction of dynamic surgical cavities.

Data flow (Su, Huang & Hannaford, IROS 2019, Fig. 2):
ingest -> template -> target -> registration -> classification -> report.
"""

import logging

__version__ = "0.1.0"

# A library stays silent unless the application configures logging (the CLI does).
logging.getLogger("surgrecon_cli").addHandler(logging.NullHandler())
