"""Run a checkpoint over an event recording or a live stream:
``python detect.py ckpt=... input=FILE|udp://HOST:PORT [frames=...] [out=DIR]`` (configs in conf/)."""
from dagr_lite.apps.cli import hydra_command
from dagr_lite.apps.detect import detect

main = hydra_command("detect", detect)

if __name__ == "__main__":
    main()
