"""movie stage: MP4 and contact sheet from rendered frames (imageio-ffmpeg)."""
