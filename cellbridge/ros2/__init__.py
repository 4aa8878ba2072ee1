"""The skin for ROS 2: bags (``cellbridge record --profile ros2``) and the live graph (``cellbridge ros2``).

Importing this package needs nothing beyond cellbridge's own dependencies; its modules
that speak DDS or CDR need Cyclone DDS's Python binding (``pip install 'cellbridge[ros2]'``).
"""

DEFAULT_FRAME = "cellbridge_skin"  #: the frame of a flat skin (its layout's plane, metres, z out of the skin)
MISSING = "needs Cyclone DDS's Python binding: pip install 'cellbridge[ros2]' (make install does)"
