"""Run a checkpoint over an event recording or a live stream:
``python detect.py ckpt=... input=FILE|udp://HOST:PORT [frames=...] [out=DIR]`` (configs in conf/)."""
import hydra
from omegaconf import DictConfig

from dagr_lite.camera.app import detect
from dagr_lite.cli import user_errors


@hydra.main(config_path="conf", config_name="detect", version_base=None)
def main(cfg: DictConfig) -> None:
    with user_errors():
        detect(cfg)


if __name__ == "__main__":
    main()
