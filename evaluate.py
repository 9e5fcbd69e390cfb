"""Evaluate on a split: ``python evaluate.py [dataset=v6] [split=test]`` (configs in conf/)."""
import hydra
from omegaconf import DictConfig

from dagr_lite.cli import user_errors
from dagr_lite.engine.evaluate import evaluate


@hydra.main(config_path="conf", config_name="evaluate", version_base=None)
def main(cfg: DictConfig) -> None:
    with user_errors():
        evaluate(cfg)


if __name__ == "__main__":
    main()
