"""mono-map: uncertainty-aware monocular mapping.

Per-pixel distributions over log-spaced depth bins (Yang, Hu, Ramanan, IROS 2019),
the most confident pixels back-projected into an OctoMap, and the map compared
against a LiDAR reference.  Data flows one way:
frames -> distributions -> kept points -> map -> metrics.
"""

__version__ = "0.1.0"
