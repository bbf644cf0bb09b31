"""α_IP by image processing (3-X paper §4.2): the twin's camera renderer, the coloured-marker
detector, calibration, frame sources and offline video alignment. See docs/camera.md."""
