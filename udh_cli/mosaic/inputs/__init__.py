"""Reading a flight: frames from a folder or video, their EXIF metadata, and the lens that undistorts them."""
