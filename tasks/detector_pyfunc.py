"""MLflow's models-from-code entry of the detector (`tasks.detector_model.DetectorPyfunc`): ``mlflow.pyfunc.log_model``
logs this file as the model and runs it when the model loads."""

import mlflow

from tasks.detector_model import DetectorPyfunc

mlflow.models.set_model(DetectorPyfunc())
