"""Scene bundles: the on-disk format of a posed capture (and synthetic ground truth)."""

from core.bundle.archive import ArchiveLimits, pack_bundle, unpack_bundle
from core.bundle.reader import BundleIssue, SceneBundle, open_bundle, read_manifest, validate_bundle
from core.bundle.schema import (
    FORMAT_NAME, MANIFEST_NAME, SCHEMA_VERSION, Camera, Frame, GroundTruth, LidarSweep, Manifest,
    ObjectTrack, RelitSet,
)
from core.bundle.writer import BundleWriter

__all__ = [
    "ArchiveLimits", "BundleIssue", "BundleWriter", "Camera", "FORMAT_NAME", "Frame", "GroundTruth",
    "LidarSweep", "MANIFEST_NAME", "Manifest", "ObjectTrack", "RelitSet", "SCHEMA_VERSION",
    "SceneBundle", "open_bundle", "pack_bundle", "read_manifest", "unpack_bundle", "validate_bundle",
]
