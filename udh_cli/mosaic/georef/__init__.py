"""Putting a mosaic on the map: GPS and ground-control fits, world files, north-up GeoTIFFs."""
