"""Train a detector: ``python train.py [dataset=v6] [key=value ...]`` (configs in conf/)."""
import hydra
from omegaconf import DictConfig

from dagr_lite.cli import user_errors
from dagr_lite.engine.train import train


@hydra.main(config_path="conf", config_name="train", version_base=None)
def main(cfg: DictConfig) -> None:
    with user_errors():
        train(cfg)


if __name__ == "__main__":
    main()
