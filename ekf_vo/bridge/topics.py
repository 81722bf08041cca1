"""THE topic rule: which topic carries the camera images, live and in a bag.

Live (a node subscribing, a harness publishing): image_transport's naming. A camera's image
topic ``<image>`` carries ``sensor_msgs/Image`` (transport ``raw``); its compressed version
is ``<image>/compressed`` (``sensor_msgs/CompressedImage``, transport ``compressed``):
:func:`transport_topic`.

Bag (``ekf-vo-run``, the demo, the benchmarks): :func:`select_camera_topics` picks, from the
bag's ``{topic: message type}``, the first raw Image topic, else the first CompressedImage
topic, and the CameraInfo topic in the image topic's namespace
(``/cam/image_raw[/compressed]`` -> ``/cam/camera_info``), else the first CameraInfo topic.
"""
from __future__ import annotations

from typing import Mapping, NamedTuple

from .common import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE

__all__ = ['TRANSPORTS', 'TopicError', 'CameraTopics', 'transport_topic',
           'select_camera_topics', 'topic_listing']

#: image transport -> message type it carries
TRANSPORTS: dict[str, str] = {'raw': IMAGE, 'compressed': COMPRESSED_IMAGE}


class TopicError(ValueError):
    """No usable (or a wrongly typed) image / CameraInfo topic, or an unknown transport."""


class CameraTopics(NamedTuple):
    """The topics to read a camera from: images, their transport and the CameraInfo."""

    image: str       #: topic carrying the images (``.../compressed`` for that transport)
    transport: str   #: 'raw' (sensor_msgs/Image) or 'compressed' (CompressedImage)
    info: str        #: CameraInfo topic


def transport_topic(image_topic: str, transport: str = 'raw') -> str:
    """The topic carrying ``image_topic`` over ``transport`` ('raw' | 'compressed').

    image_transport's convention: ``raw`` is ``image_topic`` itself, ``compressed`` is
    ``<image_topic>/compressed``. Works for relative names (``image`` ->
    ``image/compressed``, what vo_node subscribes) and absolute ones.
    """
    if transport not in TRANSPORTS:
        raise TopicError(f"image transport {transport!r}: expected one of {list(TRANSPORTS)}")
    return image_topic if transport == 'raw' else f"{image_topic.rstrip('/')}/compressed"


def topic_listing(topics: Mapping[str, str]) -> str:
    """``'/a [type], /b [type]'`` (or ``'none'``) of a bag's ``{topic: message type}``."""
    return ', '.join(f'{t} [{m}]' for t, m in topics.items()) or 'none'


def select_camera_topics(topics: Mapping[str, str], image_topic: str | None = None,
                         info_topic: str | None = None) -> CameraTopics:
    """The camera topics of a bag, given its ``{topic: message type}``.

    Without ``image_topic``: the first Image topic, else the first CompressedImage topic (in
    the mapping's order). Without ``info_topic``: ``<namespace>/camera_info`` of the image
    topic (``/cam/image_raw/compressed`` -> ``/cam/camera_info``) when present, else the first
    CameraInfo topic. Explicit choices are checked against their message type.

    Raises:
        TopicError: no (or a wrongly typed) image or CameraInfo topic.
    """
    listing = topic_listing(topics)
    by_type = {v: k for k, v in TRANSPORTS.items()}
    if image_topic is None:
        found = [t for kind in (IMAGE, COMPRESSED_IMAGE)
                 for t, m in topics.items() if m == kind]
        if not found:
            raise TopicError(f'no {IMAGE} or {COMPRESSED_IMAGE} topic in the bag (topics: '
                             f'{listing})')
        image_topic = found[0]
    elif topics.get(image_topic) not in by_type:
        raise TopicError(f'image topic {image_topic}: not an Image/CompressedImage topic of '
                         f'the bag (topics: {listing})')
    if info_topic is None:
        infos = [t for t, m in topics.items() if m == CAMERA_INFO]
        if not infos:
            raise TopicError(f'no {CAMERA_INFO} topic in the bag (topics: {listing})')
        base = image_topic.removesuffix('/compressed').rsplit('/', 1)[0]
        info_topic = next((t for t in infos if t == f'{base}/camera_info'), infos[0])
    elif topics.get(info_topic) != CAMERA_INFO:
        raise TopicError(f'info topic {info_topic}: not a CameraInfo topic of the bag '
                         f'(topics: {listing})')
    return CameraTopics(image_topic, by_type[topics[image_topic]], info_topic)
