"""The track register: what every part of the system knows about the railway itself.

- :mod:`track.network`: lines as polylines with chainage, cut into segments, with tunnels
  (GNSS outages), stations and line speeds; GeoJSON reading and writing; projection of a
  point onto a line (the geometry under map matching).
- :mod:`track.segments`: the segment bounds by line, as the services look them up.
- :mod:`track.osm`: a network from an OpenStreetMap railway extract (ways joined into one
  line per track, tunnels, stations, speeds), for ``trackfusion network import-osm``;
  :mod:`track.osm_read` reads the extract's ways and points.
- :mod:`track.versine`: the segment index statistic (chord versine SD) that both the
  on-board chain and the TRC profile import compute.

Services and simulators import this package; it imports only :mod:`schemas`. It ships no
files: a network is read from the path it is given (the demo network's is
``services.defaults.DEMO_NETWORK``).
"""
