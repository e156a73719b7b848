"""On the robot, online: F/T bias tracked from the model, payloads, causal derivatives, a C step.

- :mod:`torchcontact.online.bias`: each sensor's offset tracked against the model's predicted
  reading while no contact is active (:class:`~torchcontact.online.bias.BiasTracker`, a Kalman
  filter with a stated time constant), ``tare()``, and the offline forward-backward smoother
  over a whole log (:func:`~torchcontact.online.bias.smooth_bias`). numpy only.
- :mod:`torchcontact.online.payload`: a payload's inertial parameters, checked for physical
  consistency (:class:`~torchcontact.online.payload.Payload`), and its identification by
  recursive least squares on the sensor regressor with an excitation check
  (:class:`~torchcontact.online.payload.PayloadIdentifier`). numpy only.
- :mod:`torchcontact.online.state`: what a runtime keeps between frames (trackers, payloads,
  identification), shared by the torch estimator and the deployment runtime
  (:class:`torchcontact.runtime.EstimatorRuntime` on a C step or an ONNX step graph exported
  with ``--online``). numpy only.
- :mod:`torchcontact.online.derivatives`: causal (one-sided) Savitzky-Golay joint velocities and
  accelerations, streaming and over logs, with their delay stated. numpy only.
- :mod:`torchcontact.online.estimator`: :class:`~torchcontact.online.estimator.OnlineEstimator`,
  the torch estimator with the above (torch).
- :mod:`torchcontact.online.cstep`: the single-frame estimator with its offset and inertial
  correction as a plain C-ABI shared library (:func:`~torchcontact.online.cstep.export_c_step`,
  torch); ``EstimatorRuntime(path, backend="c")`` runs it with ctypes and numpy only.

Nothing here imports torch unless the module says so.
"""
