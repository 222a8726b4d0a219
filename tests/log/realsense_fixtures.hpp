// `rs-enumerate-devices -c` output of a D435i and a D455, in the layout of
// librealsense's tools/enumerate-devices/rs-enumerate-devices.cpp (tabs and
// column widths as it prints them). The numbers are representative, NOT a
// real unit's: written for these tests (a nominal calibration; consistent
// between the pairs of streams). Sections the importer does not read (stream
// profiles, options) are left out, as `-c` alone prints them only with other flags.
#pragma once

namespace kestrel::test {

inline const char* const kRealSenseD435iDump = R"rs(Device info: 
    Name                          : 	Intel RealSense D435I
    Serial Number                 : 	843112070123
    Firmware Version              : 	5.13.0.50
    Product Line                  : 	D400

Intrinsic Parameters:

 Intrinsic of "Color" / 640x480 / {RGB8/RGBA8/BGR8/BGRA8/Y16/YUYV}
  Width:      	640
  Height:     	480
  PPX:        	321.17333984375
  PPY:        	240.62467956543
  Fx:         	615.896179199219
  Fy:         	616.076416015625
  Distortion: 	Inverse Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	54.91 x 42.57

 Intrinsic of "Color" / 1280x720 / {RGB8/RGBA8/BGR8/BGRA8/Y16/YUYV}
  Width:      	1280
  Height:     	720
  PPX:        	641.760009765625
  PPY:        	360.937042236328
  Fx:         	923.844299316406
  Fy:         	924.114624023438
  Distortion: 	Inverse Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	69.42 x 42.57

 Intrinsic of "Depth" / 640x480 / {Z16}
  Width:      	640
  Height:     	480
  PPX:        	320.437072753906
  PPY:        	237.626480102539
  Fx:         	384.902587890625
  Fy:         	384.902587890625
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	79.48 x 63.89

 Intrinsic of "Depth" / 848x480 / {Z16}
  Width:      	848
  Height:     	480
  PPX:        	424.495788574219
  PPY:        	237.697021484375
  Fx:         	427.877685546875
  Fy:         	427.877685546875
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	89.48 x 58.58

 Intrinsic of "Infrared 1" / 640x480 / {Y8/Y16}
  Width:      	640
  Height:     	480
  PPX:        	320.437072753906
  PPY:        	237.626480102539
  Fx:         	384.902587890625
  Fy:         	384.902587890625
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	79.48 x 63.89

 Intrinsic of "Infrared 1" / 848x480 / {Y8/Y16}
  Width:      	848
  Height:     	480
  PPX:        	424.495788574219
  PPY:        	237.697021484375
  Fx:         	427.877685546875
  Fy:         	427.877685546875
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	89.48 x 58.58

Motion Intrinsic Parameters:

Motion Intrinsic of "Accel"	  MOTION_XYZ32F
Bias Variances: 	0.000001000000000  0.000001000000000  0.000001000000000  
Noise Variances: 	0.000540000000000  0.000540000000000  0.000540000000000  
Sensitivity : 
     1.000000       0.000000       0.000000       0.000000  
     0.000000       1.000000       0.000000       0.000000  
     0.000000       0.000000       1.000000       0.000000  


Motion Intrinsic of "Gyro"	  MOTION_XYZ32F
Bias Variances: 	0.000000100000000  0.000000100000000  0.000000100000000  
Noise Variances: 	0.000011900000000  0.000011900000000  0.000011900000000  
Sensitivity : 
     1.000000       0.000000       0.000000       0.000000  
     0.000000       1.000000       0.000000       0.000000  
     0.000000       0.000000       1.000000       0.000000  



Extrinsic Parameters:
Extrinsic from "Color"	  To	  "Color" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0  0  0  


Extrinsic from "Color"	  To	  "Depth" :
 Rotation Matrix:
   0.999982         0.00589996       0.0011        
  -0.00590259       0.99998          0.0024        
  -0.00108582      -0.00240645       0.999997      

 Translation Vector: -0.0147169855493317  -5.14659191487608e-05  -0.000375787887997105  


Extrinsic from "Depth"	  To	  "Color" :
 Rotation Matrix:
   0.999982        -0.00590259      -0.00108582    
   0.00589996       0.99998         -0.00240645    
   0.0011           0.0024           0.999997      

 Translation Vector: 0.0147160086780787  0.000137390219606459  0.000392098777229711  


Extrinsic from "Depth"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0  0  0  


Extrinsic from "Depth"	  To	  "Gyro" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: -0.00552  0.0051  0.01174  


Extrinsic from "Depth"	  To	  "Pose" :
N/A
Extrinsic from "Infrared 1"	  To	  "Color" :
 Rotation Matrix:
   0.999982        -0.00590259      -0.00108582    
   0.00589996       0.99998         -0.00240645    
   0.0011           0.0024           0.999997      

 Translation Vector: 0.0147160086780787  0.000137390219606459  0.000392098777229711  


Extrinsic from "Accel"	  To	  "Color" :
 Rotation Matrix:
   0.999982        -0.00590259      -0.00108582    
   0.00589996       0.99998         -0.00240645    
   0.0011           0.0024           0.999997      

 Translation Vector: 0.020278759963896  -0.00490168678215574  -0.0113540282909766  


Extrinsic from "Accel"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0.00552  -0.0051  -0.01174  


Extrinsic from "Gyro"	  To	  "Color" :
 Rotation Matrix:
   0.999982        -0.00590259      -0.00108582    
   0.00589996       0.99998         -0.00240645    
   0.0011           0.0024           0.999997      

 Translation Vector: 0.020278759963896  -0.00490168678215574  -0.0113540282909766  


Extrinsic from "Gyro"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0.00552  -0.0051  -0.01174  


)rs";

inline const char* const kRealSenseD455Dump = R"rs(Device info: 
    Name                          : 	Intel RealSense D455
    Serial Number                 : 	213622250456
    Firmware Version              : 	5.13.0.50
    Product Line                  : 	D400

Intrinsic Parameters:

 Intrinsic of "Color" / 640x480 / {RGB8/RGBA8/BGR8/BGRA8/Y16/YUYV}
  Width:      	640
  Height:     	480
  PPX:        	319.453430175781
  PPY:        	243.635009765625
  Fx:         	382.613616943359
  Fy:         	382.227630615234
  Distortion: 	Inverse Brown Conrady
  Coeffs:     	-0.0552862286567688  	0.0660683289170265  	-0.000686826137825847  	0.000671613309532404  	-0.0212168209254742  
  FOV (deg):  	79.82 x 64.24

 Intrinsic of "Color" / 1280x720 / {RGB8/RGBA8/BGR8/BGRA8/Y16/YUYV}
  Width:      	1280
  Height:     	720
  PPX:        	639.088989257812
  PPY:        	359.391693115234
  Fx:         	637.689331054688
  Fy:         	637.046081542969
  Distortion: 	Inverse Brown Conrady
  Coeffs:     	-0.0552862286567688  	0.0660683289170265  	-0.000686826137825847  	0.000671613309532404  	-0.0212168209254742  
  FOV (deg):  	90.21 x 58.94

 Intrinsic of "Depth" / 640x480 / {Z16}
  Width:      	640
  Height:     	480
  PPX:        	321.301452636719
  PPY:        	239.256652832031
  Fx:         	387.376770019531
  Fy:         	387.376770019531
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	79.12 x 63.56

 Intrinsic of "Depth" / 848x480 / {Z16}
  Width:      	848
  Height:     	480
  PPX:        	424.488525390625
  PPY:        	239.239776611328
  Fx:         	427.895812988281
  Fy:         	427.895812988281
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	89.48 x 58.57

 Intrinsic of "Infrared 1" / 640x480 / {Y8/Y16}
  Width:      	640
  Height:     	480
  PPX:        	321.301452636719
  PPY:        	239.256652832031
  Fx:         	387.376770019531
  Fy:         	387.376770019531
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	79.12 x 63.56

 Intrinsic of "Infrared 1" / 848x480 / {Y8/Y16}
  Width:      	848
  Height:     	480
  PPX:        	424.488525390625
  PPY:        	239.239776611328
  Fx:         	427.895812988281
  Fy:         	427.895812988281
  Distortion: 	Brown Conrady
  Coeffs:     	0  	0  	0  	0  	0  
  FOV (deg):  	89.48 x 58.57

Motion Intrinsic Parameters:

Motion Intrinsic of "Accel"	  MOTION_XYZ32F
Bias Variances: 	0.000001000000000  0.000001000000000  0.000001000000000  
Noise Variances: 	0.000540000000000  0.000540000000000  0.000540000000000  
Sensitivity : 
     1.000000       0.000000       0.000000       0.000000  
     0.000000       1.000000       0.000000       0.000000  
     0.000000       0.000000       1.000000       0.000000  


Motion Intrinsic of "Gyro"	  MOTION_XYZ32F
Bias Variances: 	0.000000100000000  0.000000100000000  0.000000100000000  
Noise Variances: 	0.000011900000000  0.000011900000000  0.000011900000000  
Sensitivity : 
     1.000000       0.000000       0.000000       0.000000  
     0.000000       1.000000       0.000000       0.000000  
     0.000000       0.000000       1.000000       0.000000  



Extrinsic Parameters:
Extrinsic from "Color"	  To	  "Color" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0  0  0  


Extrinsic from "Color"	  To	  "Depth" :
 Rotation Matrix:
   0.999997        -0.0021          -0.0009        
   0.00209892       0.999997        -0.0012        
   0.000902517      0.00119811       0.999999      

 Translation Vector: 0.0591316404898287  -5.11062990162878e-05  -0.000473261066109511  


Extrinsic from "Depth"	  To	  "Color" :
 Rotation Matrix:
   0.999997         0.00209892       0.000902517   
  -0.0021           0.999997         0.00119811    
  -0.0009          -0.0012           0.999999      

 Translation Vector: -0.0591309517621994  0.000175849470542744  0.000526417675428092  


Extrinsic from "Depth"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0  0  0  


Extrinsic from "Depth"	  To	  "Gyro" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: 0.03022  -0.0074  -0.01602  


Extrinsic from "Depth"	  To	  "Pose" :
N/A
Extrinsic from "Infrared 1"	  To	  "Color" :
 Rotation Matrix:
   0.999997         0.00209892       0.000902517   
  -0.0021           0.999997         0.00119811    
  -0.0009          -0.0012           0.999999      

 Translation Vector: -0.0591309517621994  0.000175849470542744  0.000526417675428092  


Extrinsic from "Accel"	  To	  "Color" :
 Rotation Matrix:
   0.999997         0.00209892       0.000902517   
  -0.0021           0.999997         0.00119811    
  -0.0009          -0.0012           0.999999      

 Translation Vector: -0.0893208825764002  0.00765848344524315  0.0165647176549905  


Extrinsic from "Accel"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: -0.03022  0.0074  0.01602  


Extrinsic from "Gyro"	  To	  "Color" :
 Rotation Matrix:
   0.999997         0.00209892       0.000902517   
  -0.0021           0.999997         0.00119811    
  -0.0009          -0.0012           0.999999      

 Translation Vector: -0.0893208825764002  0.00765848344524315  0.0165647176549905  


Extrinsic from "Gyro"	  To	  "Infrared 1" :
 Rotation Matrix:
   1   0   0
   0   1   0
   0   0   1

 Translation Vector: -0.03022  0.0074  0.01602  


)rs";

}  // namespace kestrel::test
