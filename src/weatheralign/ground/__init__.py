"""The ground in the weather: wet roads and snow cover, one ground state seen by the LiDAR and the cameras."""
