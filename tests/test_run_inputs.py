"""`vcfusion.run.input_files`: the files a run reads besides its scenario, shipped models included."""

from vcfusion.detection.detector_net import default_weights_path
from vcfusion.fusion.far_boxes import default_box_head_path
from vcfusion.prediction.model import default_model_path
from vcfusion.run import input_files
from vcfusion.scenario import load_scenario


def test_a_camera_run_names_the_shipped_models_its_stages_load():
    sc = load_scenario("accident_ar")
    assert sc.fusion.enabled and sc.fusion.detector != "oracle" and sc.fusion.refine_boxes
    files = input_files(sc)
    assert files["detector_weights"] == default_weights_path() and files["detector_weights"].is_file()
    assert files["box_head_weights"] == default_box_head_path() and files["box_head_weights"].is_file()
    assert files["prediction_model"] == default_model_path()


def test_a_traffic_run_names_no_camera_models():
    sc = load_scenario("accident")
    sc = sc.model_copy(update={"fusion": sc.fusion.model_copy(update={"enabled": False})})
    assert set(input_files(sc)) == {"network", "vehicle_types", "prediction_model"}
