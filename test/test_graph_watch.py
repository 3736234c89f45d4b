# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The text of another node doubling the calibrator's output (nodes/graph_watch.py)."""

from mag_calibrator_ros.nodes.graph_watch import doubled_text

OUT, IN, OWN = '/robot1/imu/mag_corrected', '/robot1/imu/mag', '/robot1/mag_calibrator'


def test_alone_or_with_subscribers_only_says_nothing():
    assert doubled_text(OUT, OWN, [OWN], IN, []) == ''
    assert doubled_text(OUT, OWN, [], IN, []) == ''  # not yet discovered itself


def test_another_publisher_is_named_and_one_of_the_same_name_is_called_a_second_start():
    text = doubled_text(OUT, OWN, [OWN, '/robot1/recorder'], IN, [])
    assert text.startswith(f'{OUT} has another publisher: /robot1/recorder;')
    assert 'started twice' not in text
    assert 'started twice' in doubled_text(OUT, OWN, [OWN, OWN], IN, [])


def test_another_calibrator_of_the_same_input_is_named_with_what_it_publishes():
    text = doubled_text(OUT, OWN, [OWN], IN, [('/robot2/mag_calibrator',
                                               '/robot2/imu/mag_corrected')])
    assert text == (f'another calibrator corrects {IN} too: /robot2/mag_calibrator (publishes '
                    '/robot2/imu/mag_corrected); if that is not meant, stop one')
