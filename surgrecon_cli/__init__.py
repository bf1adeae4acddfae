"""surgrecon: multi-camera 3D reconstruction of dynamic surgical cavities.

Data flow (Su, Huang & Hannaford, IROS 2019, Fig. 2):
ingest -> template -> target -> registration -> classification -> report.
"""

import logging
import os

__version__ = "0.1.0"

# OpenCV reads its decode limit once, when cv2 is imported (importing this package comes
# first): no codec decodes an image larger than io/images.MAX_IMAGE_PIXELS, whatever its
# header claims to surgrecon's own header check.
IMAGE_PIXEL_LIMIT = 1 << 26
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(IMAGE_PIXEL_LIMIT))

# A library stays silent unless the application configures logging (the CLI does).
logging.getLogger("surgrecon_cli").addHandler(logging.NullHandler())
