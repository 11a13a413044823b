"""Settings from the environment (prefix ``GEOLOC_``), made once at start-up and passed down."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

REPO_ROOT = Path(__file__).resolve().parents[1]


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="GEOLOC_", env_file=None, extra="ignore")

    data_dir: Path = Field(REPO_ROOT / "index", description="FAISS snapshots, SQLite metadata, stored images")
    models_dir: Path = Field(REPO_ROOT / "models", description="the built ONNX model and fitted pipelines")
    shared_dir: Path = Field(REPO_ROOT.parent / "shared", description="read-only data and weights")
    config: str = Field("hybrid", description="named pipeline configuration")
    api_key: str | None = Field(None, description="required in X-API-Key on writes when set")
    max_upload_bytes: int = 30 * 1024 * 1024
    max_image_pixels: int = 50_000_000
