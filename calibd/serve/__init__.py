"""What the daemon serves besides its state directory: the sensor's bytes, corrected data and
results to the other programs of the host, as gpsd serves a GNSS receiver (`calibd.serve.protocol`
is the socket protocol both ends share)."""

# What ?WATCH "samples" may ask for: here, not in the protocol module, so that the command line
# builds its choices without importing the protocol (docs/architecture.md, Start-up)
SAMPLE_KINDS = ("none", "raw", "corrected")
