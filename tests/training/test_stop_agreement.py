"""SigtermAgreement's decisions after a training batch, with Lightning's answers stubbed."""

from unittest import mock

import dapm_lightning.training.signals as signals


def test_a_stop_waits_for_the_validation_that_follows_but_not_for_one_that_never_ran():
    agreement, trainer = signals.SigtermAgreement(), mock.MagicMock(world_size=1)
    agreement._trainer, agreement.received = trainer, True
    trainer._signal_connector.received_sigterm = False
    with (mock.patch.object(signals, "between_optimizer_steps", return_value=True),
          mock.patch.object(signals, "validation_follows", return_value=True)):
        agreement.agree(trainer)  # a validation follows: the stop waits for its end
        assert not trainer._signal_connector.received_sigterm
        # Lightning skipped that validation (no after_validation came) and says one follows the next batch too:
        agreement.agree(trainer)  # the stop is not put off again
        assert trainer._signal_connector.received_sigterm
