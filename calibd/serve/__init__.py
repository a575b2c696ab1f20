"""What the daemon serves besides its state directory: the sensor's bytes, corrected data and
results to the other programs of the host, as gpsd serves a GNSS receiver (`calibd.serve.protocol`
is the socket protocol both ends share)."""
