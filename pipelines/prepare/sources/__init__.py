"""The sources stage of a prepare: the recordings (videos or image folders) matched to the calibration's cameras
(``recordings``), every frame read once with its people and masks (``observe``), from keypoint files and mask images
or from mediapipe's BlazePose and segmenter (``detect``), whose results are kept on disk (``detections``)."""
